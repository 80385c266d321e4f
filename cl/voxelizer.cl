/* Gaussian voxelizer: the field mu(x) = sum_i rho_i exp(-d^T P_i d / 2), d = x - p_i, on a regular
 * grid (or any axis-aligned block of one) and at arbitrary points, and its gradients.
 *
 * Support: Gaussian i contributes at x only inside its axis-aligned box -e_i <= x - p_i <= e_i
 * (e_i = 3 sigma along each axis), tested on the very numbers d = x - p that the reference
 * computes, so kernel and reference agree on which Gaussians touch which sample.
 *
 * Gaussians are packed as GSTRIDE reals: p (3), rho, P (xx, xy, xz, yy, yz, zz), e (3), pad; the
 * binning copies them into cell order, so the forward kernels stream through them.
 * Gradients come out as 10 reals per Gaussian: dp (3), dP (6, packed as P), drho.
 *
 * Everything is a gather (no float atomics): binning is a counting sort over chunks of Gaussians
 * (a histogram per chunk, prefix sums, a fill in Gaussian order), so each cell's list holds its
 * Gaussians in index order and every output is summed in the same order on every run.
 *
 * Options: REAL (float|double), BRICK_Y, BRICK_Z (brick rows; bricks are 8 voxels along x, one
 * real8), WANT_MEAN, WANT_PREC, WANT_RHO (which gradients the backward kernels compute). */
#include "common.h"
#include "fastexp.h"

#ifndef BRICK_Y
#define BRICK_Y 8
#endif
#ifndef BRICK_Z
#define BRICK_Z 8
#endif
#define BRICK_ROWS (BRICK_Y * BRICK_Z)
/* The record sizes; clgs/ops/voxelizer.py reads them from here to lay the records out. */
#define GSTRIDE 16
#define GRADSTRIDE 10
/* cells are widened by this fraction on both sides when binning, plus a few roundings of the
 * operands, so float rounding of the cell index can never drop a Gaussian from a cell whose
 * samples it covers (the exact test follows) */
#define BIN_MARGIN ((real)1e-3)
/* REAL_EPS, mask1 and mask8 (what comparing reals gives) come from common.h */

#if defined(WANT_MEAN) || defined(WANT_PREC)
#define NEED_FIRST 1
#endif
#if defined(WANT_PREC)
#define NEED_SECOND 1
#endif

typedef struct {
    real px, py, pz, rho, pxx, pxy, pxz, pyy, pyz, pzz, ex, ey, ez;
} gauss_t;

inline gauss_t load_gauss(global const real *gs, int i)
{
    global const real *g = gs + (size_t)i * GSTRIDE;
    gauss_t r;
    r.px = g[0]; r.py = g[1]; r.pz = g[2]; r.rho = g[3];
    r.pxx = g[4]; r.pxy = g[5]; r.pxz = g[6]; r.pyy = g[7]; r.pyz = g[8]; r.pzz = g[9];
    r.ex = g[10]; r.ey = g[11]; r.ez = g[12];
    return r;
}

/* Index range [lo, hi] of cells (origin o, inverse size inv_s, n cells) met by the interval
 * [p - e, p + e], widened by BIN_MARGIN; 0 when it misses them all (or is NaN). */
inline int cell_range(real p, real e, real o, real inv_s, int n, int *lo, int *hi)
{
    /* no builtin calls: this runs for every Gaussian, most of them culled for a small block */
    real slack = BIN_MARGIN + ((p < 0 ? -p : p) + e + (o < 0 ? -o : o)) * inv_s * (4 * REAL_EPS);
    real a = (p - e - o) * inv_s - slack;
    real b = (p + e - o) * inv_s + slack;
    if (!(b >= (real)0) || !(a < (real)n))
        return 0;
    a = a > (real)0 ? a : (real)0;
    b = b < (real)(n - 1) ? b : (real)(n - 1);
    *lo = (int)a; /* truncation is floor here: both are >= 0 */
    *hi = (int)b;
    return 1;
}

/* Index range of grid samples (coordinates c[0..n-1], first c0, spacing h) that may lie in
 * [p - e, p + e]: one sample wider each side than the float estimate; callers test exactly. */
inline int sample_range(real p, real e, real c0, real inv_h, int n, int *lo, int *hi)
{
    return cell_range(p, e, c0 - (real)0.5 / inv_h, inv_h, n, lo, hi)
        ? (*lo = max(*lo - 1, 0), *hi = min(*hi + 1, n - 1), 1) : 0;
}

#define CELL_ARGS real ox, real oy, real oz, real isx, real isy, real isz, int ncx, int ncy, int ncz

inline int gauss_cells(gauss_t g, CELL_ARGS, int *x0, int *x1, int *y0, int *y1, int *z0, int *z1)
{
    return cell_range(g.px, g.ex, ox, isx, ncx, x0, x1) && cell_range(g.py, g.ey, oy, isy, ncy, y0, y1)
        && cell_range(g.pz, g.ez, oz, isz, ncz, z0, z1);
}

inline int home_cell(real p, real o, real inv_s, int n)
{
    return (int)floor(fmin(fmax((p - o) * inv_s, (real)0), (real)(n - 1)));
}

/* The cells of Gaussian i: all cells its box meets, or (home != 0) only the cell holding its
 * centre clamped into the grid, which sorts the kept Gaussians by place (for cache locality). */
inline int gauss_cells_mode(gauss_t g, int home, CELL_ARGS, int *x0, int *x1, int *y0, int *y1, int *z0, int *z1)
{
    if (!gauss_cells(g, ox, oy, oz, isx, isy, isz, ncx, ncy, ncz, x0, x1, y0, y1, z0, z1))
        return 0;
    if (home) {
        *x0 = *x1 = home_cell(g.px, ox, isx, ncx);
        *y0 = *y1 = home_cell(g.py, oy, isy, ncy);
        *z0 = *z1 = home_cell(g.pz, oz, isz, ncz);
    }
    return 1;
}

/* ------------------------------------------------------------------------------------------ */
/* Binning: counting sort of (cell, Gaussian) pairs. hist is (ncells, nchunks), zeroed by the host. */

/* also stores each Gaussian's cell box in ranges (8 ints; x0 = -1 when culled) for bin_fill */
__kernel void bin_count(global const real *gs, int n, int chunk, int nchunks, int home, CELL_ARGS, global int *hist,
                        global int *ranges)
{
    int c = get_global_id(0);
    if (c >= nchunks)
        return;
    int i1 = min(n, (c + 1) * chunk);
    for (int i = c * chunk; i < i1; i++) {
        int x0, x1, y0, y1, z0, z1;
        global int *rg = ranges + (size_t)i * 8;
        if (!gauss_cells_mode(load_gauss(gs, i), home, ox, oy, oz, isx, isy, isz, ncx, ncy, ncz, &x0, &x1, &y0, &y1, &z0, &z1)) {
            rg[0] = -1;
            continue;
        }
        rg[0] = x0; rg[1] = x1; rg[2] = y0; rg[3] = y1; rg[4] = z0; rg[5] = z1;
        for (int z = z0; z <= z1; z++)
            for (int y = y0; y <= y1; y++)
                for (int x = x0; x <= x1; x++)
                    hist[(size_t)((z * ncy + y) * ncx + x) * nchunks + c] += 1;
    }
}

/* per cell: chunk counts -> exclusive offsets within the cell (in place), and the cell's total */
__kernel void bin_cell_offsets(global int *hist, int nchunks, int ncells, global int *total)
{
    int cell = get_global_id(0);
    if (cell >= ncells)
        return;
    global int *h = hist + (size_t)cell * nchunks;
    int s = 0;
    for (int c = 0; c < nchunks; c++) {
        int t = h[c];
        h[c] = s;
        s += t;
    }
    total[cell] = s;
}

/* exclusive scan of the cell totals: start[ncells] is the length of the whole list, or -1 when
 * it would not fit in an int (the host reports that) */
__kernel void bin_scan(global const int *total, int ncells, global int *start)
{
    if (get_global_id(0) != 0)
        return;
    long s = 0;
    for (int i = 0; i < ncells; i++) {
        start[i] = (int)min(s, (long)INT_MAX);
        s += total[i];
    }
    start[ncells] = s > (long)INT_MAX ? -1 : (int)s;
}

/* list gets the Gaussian indices; when copy != 0, packed gets their GSTRIDE-real records in list
 * order too, so the forward kernels read them sequentially instead of chasing indices. */
__kernel void bin_fill(global const real *gs, int n, int chunk, int nchunks, int ncx, int ncy, global int *hist,
                       global const int *ranges, global const int *start, global int *list, int copy,
                       global real *packed)
{
    int c = get_global_id(0);
    if (c >= nchunks)
        return;
    int i1 = min(n, (c + 1) * chunk);
    for (int i = c * chunk; i < i1; i++) {
        global const int *rg = ranges + (size_t)i * 8;
        int x0 = rg[0];
        if (x0 < 0)
            continue;
        int x1 = rg[1], y0 = rg[2], y1 = rg[3], z0 = rg[4], z1 = rg[5];
        for (int z = z0; z <= z1; z++)
            for (int y = y0; y <= y1; y++)
                for (int x = x0; x <= x1; x++) {
                    int cell = (z * ncy + y) * ncx + x;
                    global int *h = hist + (size_t)cell * nchunks + c;
                    int slot = start[cell] + *h;
                    list[slot] = i;
                    if (copy)
                        vstore16(vload16(i, gs), slot, packed);
                    *h += 1;
                }
    }
}

/* Binning of a few Gaussians into a few cells (a TV patch's bricks) by a single work-item: counts,
 * prefix sums and index lists in one launch, with no host round trip for the list length (the
 * host provides room for n x ncells entries). Same lists, in Gaussian index order, as bin_count /
 * bin_fill make. */
__kernel void bin_small(global const real *gs, int n, CELL_ARGS, global int *start, global int *list)
{
    if (get_global_id(0) != 0)
        return;
    int ncells = ncx * ncy * ncz;
    for (int c = 0; c <= ncells; c++)
        start[c] = 0;
    for (int i = 0; i < n; i++) { /* counts in start[cell + 1] */
        int x0, x1, y0, y1, z0, z1;
        if (gauss_cells(load_gauss(gs, i), ox, oy, oz, isx, isy, isz, ncx, ncy, ncz, &x0, &x1, &y0, &y1, &z0, &z1))
            for (int z = z0; z <= z1; z++)
                for (int y = y0; y <= y1; y++)
                    for (int x = x0; x <= x1; x++)
                        start[(z * ncy + y) * ncx + x + 1] += 1;
    }
    for (int c = 1; c <= ncells; c++)
        start[c] += start[c - 1];
    for (int i = 0; i < n; i++) { /* start[cell] runs as the cell's cursor ... */
        int x0, x1, y0, y1, z0, z1;
        if (gauss_cells(load_gauss(gs, i), ox, oy, oz, isx, isy, isz, ncx, ncy, ncz, &x0, &x1, &y0, &y1, &z0, &z1))
            for (int z = z0; z <= z1; z++)
                for (int y = y0; y <= y1; y++)
                    for (int x = x0; x <= x1; x++)
                        list[start[(z * ncy + y) * ncx + x]++] = i;
    }
    for (int c = ncells; c > 0; c--) /* ... and ends at the next cell's start: shift back */
        start[c] = start[c - 1];
    start[0] = 0;
}

/* number of true lanes of a comparison's result */
inline int count8(mask8 m)
{
    int8 t = -convert_int8(m);
    int4 a = t.lo + t.hi;
    int2 c = a.lo + a.hi;
    return c.x + c.y;
}

/* Trim [lo, hi] to the run of sample coordinates c[lo..hi] (increasing) within p +- e: the exact
 * box test on the samples themselves, after an estimate of the range */
#define TRIM_RUN(c, p, e, lo, hi)                  \
    do {                                           \
        while ((lo) <= (hi) && (c)[lo] - (p) < -(e)) \
            (lo)++;                                \
        while ((hi) >= (lo) && (c)[hi] - (p) > (e))  \
            (hi)--;                                \
    } while (0)

/* ------------------------------------------------------------------------------------------ */
/* Grid forward: one work-item per brick (8 x BRICK_Y x BRICK_Z voxels), one real8 per x row.
 * xs/ys/zs are the sample coordinates; xs is padded to a multiple of 8 (pads are never stored).
 * Sample (z, y, x) goes to out[offset + (z * ny + y) * pitch + x] (pitch nx: a dense volume).
 * Brick b runs over entries start[b] .. start[b+1] of its list: the records themselves in
 * packed (indexed == 0, bin_fill's copy) or indices into packed in list (indexed != 0, bin_small). */

__kernel void vox_grid(global const real *packed, global const int *start, global const int *list, int indexed,
                       global const real *xs, global const real *ys, global const real *zs,
                       int nx, int ny, int nz, int nbx, int nby, int nbricks, global real *out, int pitch, int offset)
{
    int b = get_global_id(0);
    if (b >= nbricks)
        return;
    int bx = b % nbx, t = b / nbx, by = t % nby, bz = t / nby;
    int x0 = bx * 8, y0 = by * BRICK_Y, z0 = bz * BRICK_Z;
    int nyb = min(BRICK_Y, ny - y0), nzb = min(BRICK_Z, nz - z0);
    real8 acc[BRICK_ROWS];
    for (int r = 0; r < BRICK_ROWS; r++)
        acc[r] = (real8)(0);
    real cy[BRICK_Y], cz[BRICK_Z];
#if BRICK_Y == 8 && BRICK_Z == 8
    /* rows past the grid get +inf: never below a box, always above it */
    for (int r = 0; r < 8; r++) {
        cy[r] = r < nyb ? ys[y0 + r] : (real)INFINITY;
        cz[r] = r < nzb ? zs[z0 + r] : (real)INFINITY;
    }
    const real8 vy = vload8(0, cy), vz = vload8(0, cz);
#else
    for (int r = 0; r < nyb; r++)
        cy[r] = ys[y0 + r];
    for (int r = 0; r < nzb; r++)
        cz[r] = zs[z0 + r];
#endif
    const real8 cx = vload8(0, xs + x0);

    int k1 = start[b + 1];
    for (int k = start[b]; k < k1; k++) {
        gauss_t g = load_gauss(packed, indexed ? list[k] : k);
        real8 dx = cx - g.px;
        real8 w = ((dx >= -g.ex) & (dx <= g.ex)) ? (real8)(g.rho) : (real8)(0);
        /* rows inside the box: coordinates increase, so they form one run; trim both ends (the
         * same tests as the reference's, counted without branches for 8-row bricks) */
#if BRICK_Y == 8 && BRICK_Z == 8
        int zlo = count8(vz - g.pz < -g.ez), zhi = 7 - count8(vz - g.pz > g.ez);
        int ylo = count8(vy - g.py < -g.ey), yhi = 7 - count8(vy - g.py > g.ey);
#else
        int zlo = 0, zhi = nzb - 1, ylo = 0, yhi = nyb - 1;
        TRIM_RUN(cz, g.pz, g.ez, zlo, zhi);
        TRIM_RUN(cy, g.py, g.ey, ylo, yhi);
#endif
        real a = (real)-0.5 * g.pxx;
        real8 adx = a * dx;
        for (int zz = zlo; zz <= zhi; zz++) {
            real dz = cz[zz] - g.pz;
            real cz2 = (real)-0.5 * g.pzz * dz * dz;
            real bxz = -g.pxz * dz;
            real byz = -g.pyz * dz;
            for (int yy = ylo; yy <= yhi; yy++) {
                real dy = cy[yy] - g.py;
                real bb = bxz - g.pxy * dy;
                real cc = ((real)-0.5 * g.pyy * dy + byz) * dy + cz2;
                acc[zz * BRICK_Y + yy] += w * fast_exp8((adx + bb) * dx + cc);
            }
        }
    }

    for (int zz = 0; zz < nzb; zz++)
        for (int yy = 0; yy < nyb; yy++) {
            global real *o = out + offset + ((size_t)(z0 + zz) * ny + (y0 + yy)) * pitch + x0;
            real8 v = acc[zz * BRICK_Y + yy];
            if (x0 + 8 <= nx) {
                vstore8(v, 0, o);
            } else {
                real tmp[8];
                vstore8(v, 0, tmp);
                for (int l = 0; l < nx - x0; l++)
                    o[l] = tmp[l];
            }
        }
}

/* ------------------------------------------------------------------------------------------ */
/* Backward: one work-item per Gaussian gathers dL/dmu over its own box. With w = exp(-q/2):
 *   drho = sum g w,   dp = rho P sum g w d,   dP = -rho sum g w (dx^2/2, dx dy, dx dz, dy^2/2, dy dz, dz^2/2). */

typedef struct {
    real a, ax, ay, az, axx, axy, axz, ayy, ayz, azz;
} moments_t;

inline void write_grad(global real *grad, int i, gauss_t g, moments_t m)
{
    global real *o = grad + (size_t)i * GRADSTRIDE;
#ifdef WANT_MEAN
    o[0] = g.rho * (g.pxx * m.ax + g.pxy * m.ay + g.pxz * m.az);
    o[1] = g.rho * (g.pxy * m.ax + g.pyy * m.ay + g.pyz * m.az);
    o[2] = g.rho * (g.pxz * m.ax + g.pyz * m.ay + g.pzz * m.az);
#else
    o[0] = o[1] = o[2] = (real)0;
#endif
#ifdef WANT_PREC
    o[3] = (real)-0.5 * g.rho * m.axx;
    o[4] = -g.rho * m.axy;
    o[5] = -g.rho * m.axz;
    o[6] = (real)-0.5 * g.rho * m.ayy;
    o[7] = -g.rho * m.ayz;
    o[8] = (real)-0.5 * g.rho * m.azz;
#else
    o[3] = o[4] = o[5] = o[6] = o[7] = o[8] = (real)0;
#endif
#ifdef WANT_RHO
    o[9] = m.a;
#else
    o[9] = (real)0;
#endif
}

inline real hsum8(real8 v)
{
    real4 s = v.lo + v.hi;
    real2 u = s.lo + s.hi;
    return u.x + u.y;
}

/* The moments of Gaussian g against dL/dmu over the grid samples inside its box. gout holds sample
 * (z, y, x) at gout[(z * ny + y) * pitch + x]; padded != 0: every row is readable (and zero) for 8
 * entries past nx, so the last segment needs no gather. */
inline moments_t grid_moments(gauss_t g, global const real *xs, global const real *ys, global const real *zs,
                              int nx, int ny, int nz, global const real *gout, int pitch, const int padded)
{
    moments_t m = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    int x0, x1, y0, y1, z0, z1;
    /* sample ranges from the first coordinate and the spacing, then exact tests on the samples */
    real hx = nx > 1 ? xs[1] - xs[0] : (real)1, hy = ny > 1 ? ys[1] - ys[0] : (real)1,
         hz = nz > 1 ? zs[1] - zs[0] : (real)1;
    if (!(sample_range(g.px, g.ex, xs[0], (real)1 / hx, nx, &x0, &x1)
          && sample_range(g.py, g.ey, ys[0], (real)1 / hy, ny, &y0, &y1)
          && sample_range(g.pz, g.ez, zs[0], (real)1 / hz, nz, &z0, &z1)))
        return m;
    /* trim the estimates to the exact runs of samples inside the box */
    TRIM_RUN(xs, g.px, g.ex, x0, x1);
    TRIM_RUN(ys, g.py, g.ey, y0, y1);
    TRIM_RUN(zs, g.pz, g.ez, z0, z1);
    real a = (real)-0.5 * g.pxx;
    /* per-lane sums, reduced once at the end; the y moments of a z plane are summed first and
     * weighted by dz once per plane */
    real8 v_a = (real8)(0), v_ax = v_a, v_ay = v_a, v_az = v_a, v_axx = v_a, v_axy = v_a, v_axz = v_a,
          v_ayy = v_a, v_ayz = v_a, v_azz = v_a;
    for (int z = z0; z <= z1; z++) {
        real dz = zs[z] - g.pz;
        real cz2 = (real)-0.5 * g.pzz * dz * dz;
        real bxz = -g.pxz * dz;
        real byz = -g.pyz * dz;
        real8 t0 = (real8)(0), t1 = t0, t2 = t0, u0 = t0, u1 = t0, w0 = t0;
        for (int y = y0; y <= y1; y++) {
            real dy = ys[y] - g.py;
            real bb = bxz - g.pxy * dy;
            real cc = ((real)-0.5 * g.pyy * dy + byz) * dy + cz2;
            global const real *grow = gout + ((size_t)z * ny + y) * pitch;
            real8 s0 = (real8)(0), s1 = (real8)(0), s2 = (real8)(0);
            for (int x = x0; x <= x1; x += 8) {
                real8 dx = vload8(0, xs + x) - g.px;
                real8 gv;
                if (padded || x + 8 <= nx) {
                    gv = vload8(0, grow + x);
                } else {
                    real tmp[8];
                    for (int l = 0; l < 8; l++)
                        tmp[l] = x + l < nx ? grow[x + l] : (real)0;
                    gv = vload8(0, tmp);
                }
                real8 e = fast_exp8((a * dx + bb) * dx + cc);
                real8 ge = ((dx >= -g.ex) & (dx <= g.ex)) ? gv * e : (real8)(0);
                s0 += ge;
#ifdef NEED_FIRST
                s1 += ge * dx;
#endif
#ifdef NEED_SECOND
                s2 += ge * dx * dx;
#endif
            }
            t0 += s0;
#ifdef NEED_FIRST
            t1 += dy * s0;
            u0 += s1;
#endif
#ifdef NEED_SECOND
            t2 += (dy * dy) * s0;
            u1 += dy * s1;
            w0 += s2;
#endif
        }
        v_a += t0;
#ifdef NEED_FIRST
        v_ax += u0;
        v_ay += t1;
        v_az += dz * t0;
#endif
#ifdef NEED_SECOND
        v_axx += w0;
        v_axy += u1;
        v_axz += dz * u0;
        v_ayy += t2;
        v_ayz += dz * t1;
        v_azz += (dz * dz) * t0;
#endif
    }
    m.a = hsum8(v_a);
    m.ax = hsum8(v_ax); m.ay = hsum8(v_ay); m.az = hsum8(v_az);
    m.axx = hsum8(v_axx); m.axy = hsum8(v_axy); m.axz = hsum8(v_axz);
    m.ayy = hsum8(v_ayy); m.ayz = hsum8(v_ayz); m.azz = hsum8(v_azz);
    return m;
}

/* sorted != 0: order lists the n Gaussians whose box meets the grid, sorted by place (see
 * gauss_cells_mode): neighbours in the queue then read neighbouring rows of gout, which keeps them
 * in cache (large grids). sorted == 0: work-item k takes Gaussian k of all n (small grids, whose
 * gout stays in cache anyway); a Gaussian that misses the grid gets zeros. Each Gaussian's sums
 * are the same either way. */
__kernel void vox_grid_grad(global const real *gs, global const int *order, int sorted, int n, global const real *xs,
                            global const real *ys, global const real *zs, int nx, int ny, int nz,
                            global const real *gout, global real *grad)
{
    int k = get_global_id(0);
    if (k >= n)
        return;
    int i = sorted ? order[k] : k;
    gauss_t g = load_gauss(gs, i);
    write_grad(grad, i, g, grid_moments(g, xs, ys, zs, nx, ny, nz, gout, nx, 0));
}

/* ------------------------------------------------------------------------------------------ */
/* Points: the host sorts the points by cell and pads each cell to a multiple of 8 (pads repeat a
 * point of their cell: their outputs are dropped and their incoming gradient is zero);
 * chunk_cell gives the cell of each group of 8. */

__kernel void vox_points(global const real *packed, global const int *start,
                         global const real *X, global const real *Y, global const real *Z,
                         global const int *chunk_cell, int nchunks, global real *out)
{
    int c = get_global_id(0);
    if (c >= nchunks)
        return;
    int cell = chunk_cell[c];
    const real8 x = vload8(c, X), y = vload8(c, Y), z = vload8(c, Z);
    real8 acc = (real8)(0);
    int k1 = start[cell + 1];
    for (int k = start[cell]; k < k1; k++) {
        gauss_t g = load_gauss(packed, k);
        real8 dx = x - g.px, dy = y - g.py, dz = z - g.pz;
        real8 in = ((dx >= -g.ex) & (dx <= g.ex) & (dy >= -g.ey) & (dy <= g.ey) & (dz >= -g.ez) & (dz <= g.ez))
                   ? (real8)(g.rho) : (real8)(0);
        real8 q = dx * ((real)-0.5 * g.pxx * dx - g.pxy * dy - g.pxz * dz)
                + dy * ((real)-0.5 * g.pyy * dy - g.pyz * dz) + (real)-0.5 * g.pzz * dz * dz;
        acc += in * fast_exp8(q);
    }
    vstore8(acc, c, out);
}

__kernel void vox_points_grad(global const real *gs, int n, CELL_ARGS, global const int *cell_pstart,
                              global const real *X, global const real *Y, global const real *Z,
                              global const real *G, global real *grad)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    gauss_t g = load_gauss(gs, i);
    moments_t m = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    int x0, x1, y0, y1, z0, z1;
    if (gauss_cells(g, ox, oy, oz, isx, isy, isz, ncx, ncy, ncz, &x0, &x1, &y0, &y1, &z0, &z1)) {
        real8 s0 = (real8)(0), sx = s0, sy = s0, sz = s0, sxx = s0, sxy = s0, sxz = s0, syy = s0, syz = s0, szz = s0;
        for (int cz = z0; cz <= z1; cz++)
            for (int cy = y0; cy <= y1; cy++) {
                int row = (cz * ncy + cy) * ncx;
                int p1 = cell_pstart[row + x1 + 1];
                for (int p = cell_pstart[row + x0]; p < p1; p += 8) {
                    real8 dx = vload8(0, X + p) - g.px, dy = vload8(0, Y + p) - g.py, dz = vload8(0, Z + p) - g.pz;
                    real8 q = dx * ((real)-0.5 * g.pxx * dx - g.pxy * dy - g.pxz * dz)
                            + dy * ((real)-0.5 * g.pyy * dy - g.pyz * dz) + (real)-0.5 * g.pzz * dz * dz;
                    real8 e = fast_exp8(q);
                    real8 ge = ((dx >= -g.ex) & (dx <= g.ex) & (dy >= -g.ey) & (dy <= g.ey) & (dz >= -g.ez)
                                & (dz <= g.ez)) ? vload8(0, G + p) * e : (real8)(0);
                    s0 += ge;
#ifdef NEED_FIRST
                    sx += ge * dx;
                    sy += ge * dy;
                    sz += ge * dz;
#endif
#ifdef NEED_SECOND
                    sxx += ge * dx * dx;
                    sxy += ge * dx * dy;
                    sxz += ge * dx * dz;
                    syy += ge * dy * dy;
                    syz += ge * dy * dz;
                    szz += ge * dz * dz;
#endif
                }
            }
        m.a = hsum8(s0);
        m.ax = hsum8(sx); m.ay = hsum8(sy); m.az = hsum8(sz);
        m.axx = hsum8(sxx); m.axy = hsum8(sxy); m.axz = hsum8(sxz);
        m.ayy = hsum8(syy); m.ayz = hsum8(syz); m.azz = hsum8(szz);
    }
    write_grad(grad, i, g, m);
}

/* ------------------------------------------------------------------------------------------ */
/* The matrices every Gaussian kernel consumes, from activated scales s (N, 3) and raw quaternions
 * q (N, 4, (w, x, y, z), any norm): covariance R diag(s^2) R^T, precision R diag(1/s^2) R^T (never
 * an inverse), packed (xx, xy, xz, yy, yz, zz), and the 3-sigma box half-widths 3 sqrt(diag(cov)).
 * Same maths as clgs.ops.gaussian_math (covariance, precision, axis_extent), the tests' reference.
 * One work-item per 8 Gaussians, one real8 lane each: builtins (sqrt) are calls on PoCL, so one
 * call serves 8 Gaussians; the last group repeats Gaussian n-1 in its unused lanes (never stored). */

/* lane l: p[min(i0 + l, n - 1) * stride + k] */
inline real8 lane_load(global const real *p, int i0, int n, int stride, int k)
{
    if (i0 + 8 <= n) {
        global const real *q = p + (size_t)i0 * stride + k;
        return (real8)(q[0], q[stride], q[2 * stride], q[3 * stride], q[4 * stride], q[5 * stride],
                       q[6 * stride], q[7 * stride]);
    }
    real t[8];
    for (int l = 0; l < 8; l++)
        t[l] = p[(size_t)min(i0 + l, n - 1) * stride + k];
    return vload8(0, t);
}

inline void lane_store(global real *p, int i0, int n, int stride, int k, real8 v)
{
    real t[8];
    vstore8(v, 0, t);
    int m = min(8, n - i0);
    global real *q = p + (size_t)i0 * stride + k;
    for (int l = 0; l < m; l++)
        q[l * stride] = t[l];
}

typedef struct {
    real8 w, x, y, z; /* q / max(|q|, tiny) */
    real8 norm;       /* |q| */
    real8 r[9];       /* R, row-major */
} rot8_t;

inline rot8_t quat_rotation8(global const real *quats, int i0, int n, real tiny)
{
    rot8_t o;
    real8 w = lane_load(quats, i0, n, 4, 0), x = lane_load(quats, i0, n, 4, 1),
          y = lane_load(quats, i0, n, 4, 2), z = lane_load(quats, i0, n, 4, 3);
    o.norm = sqrt(w * w + x * x + y * y + z * z);
    real8 inv = (real)1 / (o.norm > tiny ? o.norm : (real8)(tiny));
    w *= inv; x *= inv; y *= inv; z *= inv;
    o.w = w; o.x = x; o.y = y; o.z = z;
    o.r[0] = 1 - 2 * (y * y + z * z); o.r[1] = 2 * (x * y - w * z); o.r[2] = 2 * (x * z + w * y);
    o.r[3] = 2 * (x * y + w * z); o.r[4] = 1 - 2 * (x * x + z * z); o.r[5] = 2 * (y * z - w * x);
    o.r[6] = 2 * (x * z - w * y); o.r[7] = 2 * (y * z + w * x); o.r[8] = 1 - 2 * (x * x + y * y);
    return o;
}

/* packed R diag(d) R^T, stored for Gaussians i0.. */
inline void store_rdr(const real8 *r, real8 d0, real8 d1, real8 d2, global real *out, int i0, int n)
{
    real8 a0 = r[0] * d0, a1 = r[1] * d1, a2 = r[2] * d2;
    real8 b0 = r[3] * d0, b1 = r[4] * d1, b2 = r[5] * d2;
    lane_store(out, i0, n, 6, 0, a0 * r[0] + a1 * r[1] + a2 * r[2]);
    lane_store(out, i0, n, 6, 1, a0 * r[3] + a1 * r[4] + a2 * r[5]);
    lane_store(out, i0, n, 6, 2, a0 * r[6] + a1 * r[7] + a2 * r[8]);
    lane_store(out, i0, n, 6, 3, b0 * r[3] + b1 * r[4] + b2 * r[5]);
    lane_store(out, i0, n, 6, 4, b0 * r[6] + b1 * r[7] + b2 * r[8]);
    lane_store(out, i0, n, 6, 5, (r[6] * d0) * r[6] + (r[7] * d1) * r[7] + (r[8] * d2) * r[8]);
}

/* want: bit 0 covariance, bit 1 precision, bit 2 half-widths (from the covariance's diagonal, as
 * axis_extent); outputs not wanted are not touched (any buffer may be passed) */
__kernel void cov_prec(global const real *scales, global const real *quats, int n, int want, real tiny,
                       global real *cov, global real *prec, global real *extent)
{
    int i0 = get_global_id(0) * 8;
    if (i0 >= n)
        return;
    rot8_t q = quat_rotation8(quats, i0, n, tiny);
    const real8 *r = q.r;
    real8 s0 = lane_load(scales, i0, n, 3, 0), s1 = lane_load(scales, i0, n, 3, 1), s2 = lane_load(scales, i0, n, 3, 2);
    real8 d0 = s0 * s0, d1 = s1 * s1, d2 = s2 * s2;
    if (want & 1)
        store_rdr(r, d0, d1, d2, cov, i0, n);
    if (want & 4) {
        real8 vx = (r[0] * d0) * r[0] + (r[1] * d1) * r[1] + (r[2] * d2) * r[2];
        real8 vy = (r[3] * d0) * r[3] + (r[4] * d1) * r[4] + (r[5] * d2) * r[5];
        real8 vz = (r[6] * d0) * r[6] + (r[7] * d1) * r[7] + (r[8] * d2) * r[8];
        lane_store(extent, i0, n, 3, 0, 3 * sqrt(vx > 0 ? vx : (real8)(0)));
        lane_store(extent, i0, n, 3, 1, 3 * sqrt(vy > 0 ? vy : (real8)(0)));
        lane_store(extent, i0, n, 3, 2, 3 * sqrt(vz > 0 ? vz : (real8)(0)));
    }
    if (want & 2)
        store_rdr(r, (real)1 / d0, (real)1 / d1, (real)1 / d2, prec, i0, n);
}

/* one packed gradient g of M = R D R^T: with F its symmetric matrix (off-diagonal entries halved),
 * dL/dR += 2 F R D and dL/dD_k = (R^T F R)_kk, returned in dd */
inline void rdr_grad(const real8 *r, global const real *g, int i0, int n, real8 d0, real8 d1, real8 d2,
                     real8 *a, real8 *dd)
{
    real8 f00 = lane_load(g, i0, n, 6, 0), f01 = (real)0.5 * lane_load(g, i0, n, 6, 1),
          f02 = (real)0.5 * lane_load(g, i0, n, 6, 2), f11 = lane_load(g, i0, n, 6, 3),
          f12 = (real)0.5 * lane_load(g, i0, n, 6, 4), f22 = lane_load(g, i0, n, 6, 5);
    real8 d[3] = {d0, d1, d2};
    for (int k = 0; k < 3; k++) {
        real8 t0 = f00 * r[k] + f01 * r[3 + k] + f02 * r[6 + k]; /* (F R)_0k */
        real8 t1 = f01 * r[k] + f11 * r[3 + k] + f12 * r[6 + k];
        real8 t2 = f02 * r[k] + f12 * r[3 + k] + f22 * r[6 + k];
        dd[k] = r[k] * t0 + r[3 + k] * t1 + r[6 + k] * t2;
        real8 d2k = 2 * d[k];
        a[k] += t0 * d2k;
        a[3 + k] += t1 * d2k;
        a[6 + k] += t2 * d2k;
    }
}

/* Gradients to scales and quaternions from the packed gradients of the covariance (has & 1) and
 * of the precision (has & 2). */
__kernel void cov_prec_grad(global const real *scales, global const real *quats, int n, int has, real tiny,
                            global const real *g_cov, global const real *g_prec, global real *d_scales,
                            global real *d_quats)
{
    int i0 = get_global_id(0) * 8;
    if (i0 >= n)
        return;
    rot8_t q = quat_rotation8(quats, i0, n, tiny);
    const real8 *r = q.r;
    real8 s0 = lane_load(scales, i0, n, 3, 0), s1 = lane_load(scales, i0, n, 3, 1), s2 = lane_load(scales, i0, n, 3, 2);
    real8 a[9];
    for (int k = 0; k < 9; k++)
        a[k] = (real8)(0);
    real8 ds0 = (real8)(0), ds1 = ds0, ds2 = ds0, dd[3];
    if (has & 1) { /* D = s^2: dD/ds = 2 s */
        rdr_grad(r, g_cov, i0, n, s0 * s0, s1 * s1, s2 * s2, a, dd);
        ds0 += 2 * s0 * dd[0]; ds1 += 2 * s1 * dd[1]; ds2 += 2 * s2 * dd[2];
    }
    if (has & 2) { /* D = 1/s^2: dD/ds = -2 D / s */
        real8 p0 = (real)1 / (s0 * s0), p1 = (real)1 / (s1 * s1), p2 = (real)1 / (s2 * s2);
        rdr_grad(r, g_prec, i0, n, p0, p1, p2, a, dd);
        ds0 -= 2 * p0 / s0 * dd[0]; ds1 -= 2 * p1 / s1 * dd[1]; ds2 -= 2 * p2 / s2 * dd[2];
    }
    lane_store(d_scales, i0, n, 3, 0, ds0);
    lane_store(d_scales, i0, n, 3, 1, ds1);
    lane_store(d_scales, i0, n, 3, 2, ds2);
    /* through R(u), u = (w, x, y, z) */
    real8 w = q.w, x = q.x, y = q.y, z = q.z;
    real8 du0 = 2 * (-z * a[1] + y * a[2] + z * a[3] - x * a[5] - y * a[6] + x * a[7]);
    real8 du1 = 2 * (y * a[1] + z * a[2] + y * a[3] - 2 * x * a[4] - w * a[5] + z * a[6] + w * a[7] - 2 * x * a[8]);
    real8 du2 = 2 * (-2 * y * a[0] + x * a[1] + w * a[2] + x * a[3] + z * a[5] - w * a[6] + z * a[7] - 2 * y * a[8]);
    real8 du3 = 2 * (-2 * z * a[0] - w * a[1] + x * a[2] + w * a[3] - 2 * z * a[4] + y * a[5] + x * a[6] + y * a[7]);
    /* u = q / |q|: dq = (du - u (u . du)) / |q|; where the norm is clamped, u = q / tiny */
    real8 big = q.norm > tiny ? (real8)(1) : (real8)(0);
    real8 proj = big * (w * du0 + x * du1 + y * du2 + z * du3);
    real8 inv = (real)1 / (q.norm > tiny ? q.norm : (real8)(tiny));
    lane_store(d_quats, i0, n, 4, 0, (du0 - w * proj) * inv);
    lane_store(d_quats, i0, n, 4, 1, (du1 - x * proj) * inv);
    lane_store(d_quats, i0, n, 4, 2, (du2 - y * proj) * inv);
    lane_store(d_quats, i0, n, 4, 3, (du3 - z * proj) * inv);
}
