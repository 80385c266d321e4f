/* Per-tile Gaussian lists built on the device: a deterministic counting sort, no atomics.
 *
 * Input: one int4 box per (view, Gaussian), (u0, u1, v0, v1) inclusive pixel ranges already
 * clipped to the detector; u0 > u1 marks a culled Gaussian. Tiles are TW x TH pixels.
 *
 * The Gaussians are cut into chunks of consecutive indices. Each work-item owns one (chunk, view)
 * column of the histogram `hist[view][chunk][tile]`, so it counts without atomics; `bin_totals`
 * turns each tile's counts into per-chunk offsets, `bin_scan` gives every (view, tile) list its
 * start, and `fill` (gaussian_project.cl) writes each chunk's Gaussians, in index order, at its own offsets. Every
 * list therefore holds its Gaussians in increasing index order, whatever the device does, and the
 * forward sums are bitwise reproducible. */
#ifndef TW
#define TW 8
#endif
#ifndef TH
#define TH 16
#endif

__kernel void bin_hist(const int N, const int chunk, const int nchunks, const int ntx, const int ntiles,
                       __global const int4 *box, __global int *hist)
{
    const int c = get_global_id(0);
    const int view = get_global_id(1);
    if (c >= nchunks) return;
    __global int *h = hist + ((size_t)view * nchunks + c) * ntiles;
    for (int t = 0; t < ntiles; t++) h[t] = 0;
    const int g1 = min(N, (c + 1) * chunk);
    for (int g = c * chunk; g < g1; g++) {
        const int4 b = box[(size_t)view * N + g];
        if (b.x > b.y) continue;
        const int tx0 = b.x / TW, tx1 = b.y / TW, ty0 = b.z / TH, ty1 = b.w / TH;
        for (int ty = ty0; ty <= ty1; ty++)
            for (int tx = tx0; tx <= tx1; tx++) h[ty * ntx + tx] += 1;
    }
}

__kernel void bin_totals(const int nchunks, const int ntiles, __global int *hist, __global int *totals)
{
    const int t = get_global_id(0);
    const int view = get_global_id(1);
    if (t >= ntiles) return;
    __global int *h = hist + (size_t)view * nchunks * ntiles + t;
    int s = 0;
    for (int c = 0; c < nchunks; c++) {
        const int x = h[(size_t)c * ntiles];
        h[(size_t)c * ntiles] = s;
        s += x;
    }
    totals[(size_t)view * ntiles + t] = s;
}

/* One work-item: n is at most views x tiles (a few hundred thousand), a sequential scan is cheap. */
__kernel void bin_scan(const int n, __global const int *totals, __global int *starts)
{
    if (get_global_id(0) != 0) return;
    int s = 0;
    for (int i = 0; i < n; i++) {
        starts[i] = s;
        s += totals[i];
    }
    starts[n] = s;
}

/* The fill pass, which also copies each Gaussian's record next to its list entry, is the
 * `fill` kernel of gaussian_project.cl (it needs the record layout). */
