"""Reconstruction quality, computed as R2-Gaussian computes it so that numbers compare with papers.

Normalisation (3-D metrics): both volumes are mapped with the *truth's* range,
``v' = (v - min(truth)) / (max(truth) - min(truth))``, so the truth spans exactly [0, 1] and the
prediction is not clipped (over- and undershoot count as error). R2-Gaussian's datasets are
normalised to [0, 1] (``data_generator/synthetic_dataset/process_raw_data.py``), so on them this
equals their raw-value ``metric_vol`` with ``pixel_max = 1`` (``r2_gaussian/utils/image_utils.py``)
up to resampling leaving the maximum a little under 1; ``data_range=1`` reproduces their raw-value
figures exactly (values divided by ``data_range``, no shift).

* ``psnr3d = 10 log10(1 / MSE)`` over all voxels (inf for identical volumes).
* ``ssim3d``: for each axis (z, y, x) the 2-D SSIM of every slice along it, averaged over the
  slices whose normalised truth is not all zero; then the mean of the three axis means. The 2-D
  SSIM is R2-Gaussian's (``loss_utils.ssim``): an 11 x 11 Gaussian window, sigma 1.5, C1 = 0.01^2,
  C2 = 0.03^2 (data range 1), population (not sample) variances, the slice zero-padded at its
  borders and the SSIM map averaged over *every* pixel. ``implementation="skimage"`` instead
  calls :func:`skimage.metrics.structural_similarity` with the same window, constants and
  variances; it differs only in border handling (mirror padding, and a 5-pixel border left out
  of the mean), so its values differ slightly from the papers'.
* Masked variants (e.g. a dilated bone mask): PSNR from the MSE over the mask's voxels; SSIM as
  the mean, over the mask's voxels, of the per-voxel SSIM map of each axis, averaged over the
  three axes. The normalisation still uses the whole truth's range, so masked and unmasked
  numbers are on the same scale.
* Projections (2-D, ``projection_psnr``/``projection_ssim``): as R2-Gaussian's ``metric_proj``,
  each view of the truth and of the prediction is divided by its *own* maximum, the 2-D PSNR
  (peak 1) or SSIM computed per view, views whose truth is all zero skipped, then averaged.
* ``surface_distance`` (mm) lives in :mod:`clgs.mesh.surface` and is re-exported here.
"""
from __future__ import annotations

import math

import numpy as np

from clgs.errors import ClgsError

__all__ = ["psnr3d", "ssim3d", "masked_psnr3d", "masked_ssim3d", "ssim_maps", "projection_psnr",
           "projection_ssim", "evaluate_volume", "surface_distance", "MetricError",
           "SSIM_WINDOW", "SSIM_SIGMA", "SSIM_C1", "SSIM_C2", "gaussian_window"]

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


class MetricError(ClgsError, ValueError):
    """Inputs a metric cannot be computed on (shapes differ, constant truth, empty mask, NaN)."""


def tv_count(shape) -> int:
    """Number of neighbour differences in a (Z, Y, X) block, over the three axes together (the
    denominator of R2-Gaussian's total variation)."""
    nz, ny, nx = (int(n) for n in shape)
    total = nx * ny * nz
    return sum(total // n * (n - 1) for n in (nx, ny, nz) if n > 0)


def _pair(pred, truth, ndim=3):
    p = np.asarray(pred, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if t.ndim != ndim or p.shape != t.shape:
        raise MetricError(f"prediction {p.shape} and truth {t.shape} must be {ndim}-D arrays of the same shape")
    if not np.all(np.isfinite(p)):
        raise MetricError("the prediction contains NaN or Inf")
    if not np.all(np.isfinite(t)):
        raise MetricError("the truth contains NaN or Inf")
    return p, t


def _normalised(pred, truth, data_range=None):
    p, t = _pair(pred, truth)
    if data_range is not None:
        r = float(data_range)
        if not (math.isfinite(r) and r > 0):
            raise MetricError(f"data_range must be a positive number, got {data_range!r}")
        return p / r, t / r
    lo, hi = float(t.min()), float(t.max())
    if not hi > lo:
        raise MetricError(f"the truth is constant ({lo}); metrics normalised by its range are undefined")
    return (p - lo) / (hi - lo), (t - lo) / (hi - lo)


def _mask(mask, shape):
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise MetricError(f"mask {m.shape} must have the volume's shape {tuple(shape)}")
    m = m.astype(bool)
    if not m.any():
        raise MetricError("the mask is empty; nothing to measure")
    return m


def _psnr_from_mse(mse: float, peak: float = 1.0) -> float:
    return math.inf if mse <= 0 else float(10.0 * math.log10(peak * peak / mse))


def psnr3d(pred, truth, mask=None, data_range=None) -> float:
    """3-D PSNR (dB) after normalising both by the truth's range; inf when identical.

    ``data_range``: divide by this number instead (no shift); ``data_range=1`` reproduces
    R2-Gaussian's raw-value ``metric_vol`` on any volume."""
    p, t = _normalised(pred, truth, data_range)
    d2 = (p - t) ** 2
    if mask is not None:
        d2 = d2[_mask(mask, t.shape)]
    return _psnr_from_mse(float(d2.mean()))


def masked_psnr3d(pred, truth, mask) -> float:
    """PSNR over the voxels of a boolean ``mask`` (normalised by the whole truth's range)."""
    return psnr3d(pred, truth, mask=mask)


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """The normalised 1D Gaussian window (float64) of every SSIM in clgs: the metric here, the
    training loss (:mod:`clgs.fit.losses`) and its OpenCL kernel (:mod:`clgs.ops.ssim`)."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    w = np.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return w / w.sum()


def _ssim_map_axis(p, t, axis: int) -> np.ndarray:
    """Per-voxel 2-D SSIM map of every slice along ``axis`` (R2-Gaussian's zero-padded window)."""
    from scipy.ndimage import correlate1d

    w = gaussian_window()
    plane = [a for a in range(3) if a != axis]

    def blur(a):
        for ax in plane:
            a = correlate1d(a, w, axis=ax, mode="constant", cval=0.0)
        return a

    mu_p, mu_t = blur(p), blur(t)
    s_pp = blur(p * p) - mu_p ** 2
    s_tt = blur(t * t) - mu_t ** 2
    s_pt = blur(p * t) - mu_p * mu_t
    num = (2 * mu_p * mu_t + SSIM_C1) * (2 * s_pt + SSIM_C2)
    den = (mu_p ** 2 + mu_t ** 2 + SSIM_C1) * (s_pp + s_tt + SSIM_C2)
    return num / den


def ssim_maps(pred, truth):
    """The three per-voxel SSIM maps (slices along z, y, x) of the normalised volumes."""
    p, t = _normalised(pred, truth)
    return [_ssim_map_axis(p, t, a) for a in range(3)]


def _skimage_slice_ssim(p2, t2, full=False):
    from skimage.metrics import structural_similarity

    if min(p2.shape) < SSIM_WINDOW:
        raise MetricError(f"implementation='skimage' needs slices of at least {SSIM_WINDOW} pixels, got {p2.shape}")
    return structural_similarity(t2, p2, data_range=1.0, gaussian_weights=True, sigma=SSIM_SIGMA,
                                 use_sample_covariance=False, full=full)


def _slabs(n_slices: int, slice_size: int, budget: int = 4_000_000):
    """Ranges of slices whose float64 temporaries stay within ~``budget`` elements each."""
    step = max(1, budget // max(1, slice_size))
    return [(s, min(s + step, n_slices)) for s in range(0, n_slices, step)]


def ssim3d(pred, truth, mask=None, return_axes: bool = False, implementation: str = "r2gaussian",
           data_range=None):
    """3-D SSIM: mean over the 3 axes of the mean 2-D SSIM of the slices (see the module doc).

    ``return_axes=True`` returns ``(ssim, [ssim_z, ssim_y, ssim_x])``. With a ``mask`` the SSIM
    maps are averaged over the mask's voxels instead of over slices. Slices are processed in
    slabs, so memory stays bounded for large volumes. ``data_range`` as in :func:`psnr3d`.
    """
    if implementation not in ("r2gaussian", "skimage"):
        raise MetricError(f"implementation must be 'r2gaussian' or 'skimage', got {implementation!r}")
    p, t = _normalised(pred, truth, data_range)
    m = None if mask is None else _mask(mask, t.shape)
    axes = []
    for axis in range(3):
        pm, tm = np.moveaxis(p, axis, 0), np.moveaxis(t, axis, 0)
        mm = None if m is None else np.moveaxis(m, axis, 0)
        per_slice, total, count = [], 0.0, 0
        for a, b in _slabs(tm.shape[0], tm[0].size):
            if implementation == "r2gaussian":
                smap = _ssim_map_axis(pm[a:b], tm[a:b], 0)
            elif mm is not None:
                smap = np.stack([_skimage_slice_ssim(x, y, full=True)[1] for x, y in zip(pm[a:b], tm[a:b])])
            else:
                per_slice.extend(_skimage_slice_ssim(x, y) for x, y in zip(pm[a:b], tm[a:b]))
                continue
            if mm is not None:
                total += float(smap[mm[a:b]].sum())
                count += int(mm[a:b].sum())
            else:
                per_slice.extend(smap.mean(axis=(1, 2)))
        if mm is not None:
            axes.append(total / count)
            continue
        keep = tm.reshape(tm.shape[0], -1).max(axis=1) > 0
        axes.append(float(np.asarray(per_slice)[keep].mean()))
    value = float(np.mean(axes))
    return (value, axes) if return_axes else value


def masked_ssim3d(pred, truth, mask, implementation: str = "r2gaussian") -> float:
    """SSIM averaged over the voxels of a boolean ``mask`` (see the module doc)."""
    return ssim3d(pred, truth, mask=mask, implementation=implementation)


def _views(pred, truth):
    p, t = _pair(pred, truth)
    keep = t.reshape(len(t), -1).max(axis=1) > 0
    if not keep.any():
        raise MetricError("every truth projection is zero; projection metrics are undefined")
    out = []
    for i in np.nonzero(keep)[0]:
        pmax = p[i].max()
        out.append((int(i), p[i] / pmax if pmax > 0 else p[i], t[i] / t[i].max()))
    return out


def projection_psnr(pred, truth, per_view: bool = False):
    """Mean 2-D PSNR over views (n, V, U), each view normalised by its own maximum (as R2-Gaussian)."""
    vals = [_psnr_from_mse(float(((a - b) ** 2).mean())) for _, a, b in _views(pred, truth)]
    mean = float(np.mean(vals))  # an identical view (inf dB) makes the mean inf, as in R2-Gaussian
    return (mean, vals) if per_view else mean


def projection_ssim(pred, truth, per_view: bool = False):
    """Mean 2-D SSIM over views (n, V, U), each view normalised by its own maximum (as R2-Gaussian)."""
    vals = []
    for _, a, b in _views(pred, truth):
        smap = _ssim_map_axis(a[None], b[None], 0)
        vals.append(float(smap.mean()))
    mean = float(np.mean(vals))
    return (mean, vals) if per_view else mean


def surface_distance(mesh_a, mesh_b, **kwargs) -> dict:
    """Symmetric surface distance in mm; see :func:`clgs.mesh.surface.surface_distance`."""
    from clgs.mesh.surface import surface_distance as _sd

    return _sd(mesh_a, mesh_b, **kwargs)


def volume_figures(pred, truth) -> dict:
    """``psnr3d`` and ``ssim3d`` of a reconstruction, for logs and reports: where the truth makes
    them undefined (constant, all zero) both are None and ``metrics_undefined`` says why, so that
    a reconstruction is never lost to its metrics. Other errors (shapes, NaN) still raise."""
    try:
        return {"psnr3d": float(psnr3d(pred, truth)), "ssim3d": float(ssim3d(pred, truth))}
    except MetricError as exc:
        if "undefined" not in str(exc):
            raise
        return {"psnr3d": None, "ssim3d": None, "metrics_undefined": str(exc)}


def evaluate_volume(pred, truth, mask=None) -> dict:
    """PSNR and SSIM (with per-axis SSIM), plus their masked versions when ``mask`` is given."""
    s, axes = ssim3d(pred, truth, return_axes=True)
    out = {"psnr3d": psnr3d(pred, truth), "ssim3d": s, "ssim3d_axes": axes}
    if mask is not None:
        out["psnr3d_masked"] = masked_psnr3d(pred, truth, mask)
        out["ssim3d_masked"] = masked_ssim3d(pred, truth, mask)
    return out
