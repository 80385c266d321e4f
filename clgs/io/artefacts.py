"""Detector faults in line integrals: stripes (rings in the slice) and zingers (single bright or
dark pixels), removed on request.

Stripes: a detector column that answers a little more or less than its flat field said adds the
same offset to every view, a vertical stripe in the sinogram and a ring around the axis in the
slice. :func:`remove_stripes` takes each row's sinogram less its 2-pixel Gaussian smoothing (the
object's own slopes across columns would hide a stripe from a median), sorts each column of that
detail by value along the views, median-filters
the sorted sinogram across columns (a stripe is an outlier among its neighbours at every rank,
while the object, once sorted, varies smoothly across columns), and puts the values back in their
views: the sorting-based filter of Vo et al. (2018). ``size`` (columns) must exceed a stripe's
width; larger sizes also smooth real fine structure.

Zingers: a stray photon or particle lights one pixel of one view. :func:`remove_zingers` compares
each pixel with the median of its 3 x 3 neighbourhood in its own view and replaces it by that
median where they differ by more than ``threshold`` (line-integral units; ``"auto"``: 8 robust
standard deviations of the difference over the whole stack).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["remove_stripes", "remove_zingers"]

AUTO_ZINGER_WIDTHS = 8.0


def remove_stripes(proj: np.ndarray, size: int = 21) -> tuple[np.ndarray, dict]:
    """(projections without vertical sinogram stripes, report) (module doc)."""
    p = np.asarray(proj, np.float32)
    size = int(size)
    if size < 3 or size % 2 == 0:
        raise ValueError(f"the stripe filter's size must be an odd number of columns >= 3, got {size}")
    if size > p.shape[2]:
        raise ValueError(f"the stripe filter's size {size} exceeds the detector's {p.shape[2]} columns")
    out = np.empty_like(p)
    # the object's own slopes across columns hide a stripe from a median (a monotonic window's
    # median is its middle): the filter works on what a 2-pixel Gaussian leaves, a stripe's scale
    smooth_part = ndimage.gaussian_filter1d(p, 2.0, axis=2, mode="nearest")
    detail = p - smooth_part
    for r in range(p.shape[1]):
        sino = detail[:, r, :]
        order = np.argsort(sino, axis=0, kind="stable")
        ranked = np.take_along_axis(sino, order, axis=0)
        smooth = ndimage.median_filter(ranked, size=(1, size), mode="reflect")
        back = np.empty_like(smooth)
        np.put_along_axis(back, order, smooth, axis=0)
        out[:, r, :] = back + smooth_part[:, r, :]
    change = np.abs(out - p)
    return out, {"method": f"sorting and a median across {size} columns", "size": size,
                 "mean_change": float(change.mean()), "max_change": float(change.max())}


def remove_zingers(proj: np.ndarray, threshold="auto") -> tuple[np.ndarray, dict]:
    """(projections with zingers replaced by their neighbourhood's median, report) (module doc)."""
    p = np.asarray(proj, np.float32)
    size = (1, min(3, p.shape[1]), min(3, p.shape[2]))
    med = ndimage.median_filter(p, size=size, mode="nearest")
    diff = p - med
    if isinstance(threshold, str):
        if threshold != "auto":
            raise ValueError(f"the zinger threshold must be a positive number or 'auto', got {threshold!r}")
        spread = 1.4826 * float(np.median(np.abs(diff - np.median(diff))))
        thr = AUTO_ZINGER_WIDTHS * spread if spread > 0 else float(np.abs(diff).max()) / 2
        how = f"auto: {AUTO_ZINGER_WIDTHS:g} robust standard deviations"
    else:
        thr = float(threshold)
        if not (np.isfinite(thr) and thr > 0):
            raise ValueError(f"the zinger threshold must be a positive number or 'auto', got {threshold!r}")
        how = "given"
    hit = np.abs(diff) > thr
    out = np.where(hit, med, p)
    return out, {"threshold": float(thr), "threshold_from": how, "pixels": int(hit.sum()),
                 "fraction": float(hit.mean())}
