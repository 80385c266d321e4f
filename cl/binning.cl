/* Per-tile Gaussian lists built on the device: a deterministic counting sort, no atomics.
 *
 * Input: one int4 box per (view, Gaussian), (u0, u1, v0, v1) inclusive pixel ranges already
 * clipped to the detector; u0 > u1 marks a culled Gaussian. Tiles are TW x TH pixels.
 *
 * The Gaussians are cut into chunks of consecutive indices. The set-up kernel (`preprocess` in
 * gaussian_project.cl) handles one (chunk, view) at a time and, once the chunk's boxes are
 * known, counts them into its own column of the histogram `hist[view][chunk][tile]`: no
 * atomics, and no separate launch reading the boxes again. `bin_offsets` turns the
 * counts into list positions and every (view, tile) list's start, and `fill`
 * (gaussian_project.cl) writes each chunk's Gaussians, in index order, at its own positions.
 * Every list therefore holds its Gaussians in increasing index order, whatever the device does,
 * and the forward sums are bitwise reproducible. */
#ifndef TW
#define TW 8
#endif
#ifndef TH
#define TH 16
#endif

/* One work-item per view: starts[view][t] is tile t's list start within the view's lists
 * (starts[view][ntiles] the view's pair count, -1 past 2^31), and every histogram entry becomes the position,
 * within the view, of its chunk's first Gaussian in that tile's list. A view's lists follow those
 * of the views before it (the users add that base themselves). Sequential: the histogram of a
 * view is a few ten thousand ints, and one launch instead of a parallel reduce + scan pair
 * costs less on a CPU. */
__kernel void bin_offsets(const int nviews, const int nchunks, const int ntiles, __global int *hist,
                          __global int *starts)
{
    const int view = get_global_id(0);
    if (view >= nviews) return;
    __global int *h = hist + (size_t)view * nchunks * ntiles;
    __global int *st = starts + (size_t)view * (ntiles + 1);
    int s = 0, over = 0;
    for (int t = 0; t < ntiles; t++) {
        st[t] = s;
        for (int c = 0; c < nchunks; c++) {
            const int x = h[(size_t)c * ntiles + t];
            h[(size_t)c * ntiles + t] = s;
            s += x;
        }
        over |= s < 0; /* more than 2^31 pairs in this view: the host raises */
    }
    st[ntiles] = over ? -1 : s;
}

/* The fill pass, which also copies each Gaussian's record next to its list entry, is the
 * `fill` kernel of gaussian_project.cl (it needs the record layout). */
