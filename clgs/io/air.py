"""Beam normalisation from the air: each view's I0 set so that the air around the object reads 0.

Flat fields are taken before or after the scan; if the beam was weaker or stronger during a
projection than during the flats (a synchrotron's decaying current, a tube warming up), every
pixel of that view reads ``-log(k)`` too much after ``-log(I / flat)``: a background, uniform over
the view, that varies from view to view. It biases the centre of mass towards the detector's
middle and leaves a disk (or cupping) in a filtered backprojection. Rescaling the view's I0 by
``k`` is subtracting that background in the log domain, so this module works on line integrals.

:func:`find_air` finds, per view, the detector columns that see only air: the view's column
profile (mean over rows), median-smoothed, is compared with its lowest level; columns within a
few noise widths of it are air (the noise width comes from the profile's own first differences).
A view needs at least :data:`MIN_AIR_COLUMNS` such columns (and 2 % of the detector). Where the
object fills a view, the view's background is taken from its neighbours in angle. This assumes the
lowest-attenuating columns are air; an object that covers every column of every view (a slab wider
than the detector) has no air to find: give ``air_columns`` or switch the normalisation off.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["find_air", "air_background", "normalise_air", "MIN_AIR_COLUMNS"]

MIN_AIR_COLUMNS = 4
NOISE_WIDTHS = 5.0


def _noise(profile: np.ndarray) -> np.ndarray:
    """Per-view noise width of a column profile (n_views, columns) from its first differences
    (robust: the object's edges are few)."""
    d = np.diff(profile, axis=1)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=1, keepdims=True)), axis=1) / np.sqrt(2.0)


def find_air(proj: np.ndarray) -> np.ndarray:
    """(n_views, columns) bool: columns that see only air in each view of ``proj`` (n_views, rows,
    columns) line integrals (see the module doc). A view with too few such columns has none."""
    p = np.asarray(proj, np.float64)
    profile = p.mean(axis=1)
    n_cols = profile.shape[1]
    smooth = ndimage.median_filter(profile, size=(1, min(5, n_cols)), mode="nearest")
    low = smooth.min(axis=1)
    spread = smooth.max(axis=1) - low
    tol = np.maximum(NOISE_WIDTHS * _noise(profile), 0.01 * spread)
    air = smooth <= (low + tol)[:, None]
    need = max(MIN_AIR_COLUMNS, int(np.ceil(0.02 * n_cols)))
    air[air.sum(axis=1) < need] = False
    return air


def air_background(proj: np.ndarray, air_columns=None) -> tuple[np.ndarray, dict]:
    """(background (n_views,), report): each view's air level in line-integral units, the median
    over its air pixels: columns ``air_columns`` (first, last exclusive) of every view if given,
    else :func:`find_air`'s. Views without air take the level of their nearest neighbours (by
    index, linearly). Raises ValueError when no view has air."""
    p = np.asarray(proj, np.float64)
    n, _, n_cols = p.shape
    if air_columns is not None:
        a, b = (int(v) for v in air_columns)
        if not (0 <= a < b <= n_cols):
            raise ValueError(f"air columns {a}:{b} lie outside the detector's 0:{n_cols}")
        mask = np.zeros((n, n_cols), bool)
        mask[:, a:b] = True
        how = f"columns {a}:{b}"
    else:
        mask = find_air(p)
        how = "found per view"
    has = mask.any(axis=1)
    if not has.any():
        raise ValueError("no view shows air (every column attenuated in every view)")
    bg = np.full(n, np.nan)
    for i in np.nonzero(has)[0]:
        bg[i] = float(np.median(p[i][:, mask[i]]))
    if not has.all():
        idx = np.arange(n)
        bg[~has] = np.interp(idx[~has], idx[has], bg[has])
    counts = mask.sum(axis=1)
    report = {"air": how, "views_without_air": int((~has).sum()),
              "air_columns_min": int(counts[has].min()), "air_columns_max": int(counts.max()),
              "background_min": float(bg.min()), "background_max": float(bg.max()),
              "background_mean": float(bg.mean())}
    return bg, report


def normalise_air(proj: np.ndarray, air_columns=None) -> tuple[np.ndarray, dict]:
    """(line integrals with each view's air at 0, report): :func:`air_background` subtracted
    (the same as rescaling each view's I0). The report holds the background per view (listed),
    its min and max."""
    bg, report = air_background(proj, air_columns)
    out = np.asarray(proj, np.float32) - bg.astype(np.float32)[:, None, None]
    report["background_per_view"] = [round(float(v), 6) for v in bg]
    return out, report
