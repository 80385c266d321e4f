"""Evaluation of a reconstruction against a simulated scan's truth: the bone iso-level, the solid
bone mask (and its outer surface) and the metrics (PSNR, SSIM, surface distance). Library code
shared by ``clgs <anatomy> ...``, :mod:`clgs.experiment` and :mod:`clgs.methods.shape_guided`."""
from __future__ import annotations
from clgs.errors import InputError

__all__ = ["surface_level", "bone_mask", "bone_surface", "evaluate_volume", "truncated_field_of_view"]


def surface_level(anatomy, truth) -> float:
    """The bone iso-level: ``scene['surface_level']`` or the upper of 3-class Otsu thresholds (Otsu's
    threshold for a truth of two values; a ValueError for a constant one)."""
    level = (anatomy.scene or {}).get("surface_level")
    if level is not None:
        return float(level)
    import numpy as np
    from skimage.filters import threshold_multiotsu

    t = np.asarray(truth, np.float32)
    sub = t[:: max(1, t.shape[0] // 64)]
    try:
        return float(threshold_multiotsu(sub, classes=3)[-1])
    except ValueError:  # two values only (a surface filled with one density): bone against air
        from skimage.filters import threshold_otsu

        if float(sub.min()) == float(sub.max()):
            raise
        return float(threshold_otsu(sub))


def bone_mask(volume, level: float, min_piece: float = 0.1):
    """The solid bone: voxels above ``level``, enclosed cavities (medullary canal, cancellous
    interior below the level) filled, pieces smaller than ``min_piece`` x the largest dropped; so
    the surface compared is the outer bone surface, not every iso-contour or speckle. (A sparse-view
    reconstruction often breaks a bone at thin cortex: keeping only the largest piece would
    measure one fragment's surface against the whole bone.)"""
    import numpy as np
    from scipy import ndimage

    mask = np.asarray(volume) > level
    labels, n = ndimage.label(mask)
    if n > 1:
        sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, n + 1))
        keep = np.flatnonzero(sizes >= min_piece * sizes.max()) + 1
        mask = np.isin(labels, keep)
    return ndimage.binary_fill_holes(mask)


def bone_surface(volume, geometry, level: float | None = None):
    """The outer bone surface (:class:`clgs.io.mesh.Mesh`, mm) of a (Z, Y, X) volume on
    ``geometry``'s grid: :func:`clgs.mesh.surface.surface_from_volume` of :func:`bone_mask` at
    ``level`` (1/mm; default, with no truth to take an iso-level from, half way between the
    volume's median and its 99.5th percentile). None when no surface separates bone from the rest
    (nothing, or everything, above the level)."""
    import numpy as np

    from clgs.mesh.surface import surface_from_volume

    vol = np.asarray(volume, np.float32)
    if level is None:
        level = 0.5 * (float(np.median(vol)) + float(np.percentile(vol, 99.5)))
    mask = bone_mask(vol, level)
    if not mask.any() or mask.all():
        return None
    return surface_from_volume(mask, geometry=geometry)


def truncated_field_of_view(scan):
    """(Z, Y, X) bool of :meth:`clgs.geometry.Geometry.field_of_view` for a scan simulated with a
    smaller detector (``meta['acquisition']['detector_fov_mm']``); None for any other scan."""
    acq = (scan.meta or {}).get("acquisition") or {}
    if not acq.get("detector_fov_mm"):
        return None
    return scan.geometry.field_of_view()


def evaluate_volume(anatomy, scan, volume) -> dict:
    """PSNR/SSIM against the scan's truth and, when the scan has the true surface, the surface
    distance (mm) from the reconstruction's outer bone surface (:func:`bone_mask`) to it."""
    from clgs import metrics
    from clgs.anatomy.simulation import as_float32

    if scan.truth is None:
        raise InputError("the scan has no truth volume to evaluate against (only simulated scans have one)")
    vol = as_float32(volume)
    if vol.shape != scan.truth.shape:
        raise InputError(f"reconstruction {vol.shape} and truth {scan.truth.shape} differ in shape")
    out = metrics.volume_figures(vol, scan.truth)
    if out["psnr3d"] is not None:
        out = metrics.evaluate_volume(vol, scan.truth)
        fov = truncated_field_of_view(scan)
        if fov is not None and fov.any():
            # a truncated scan is judged where it measured every line (the whole-volume figures
            # include bone that no view saw); evaluate an untruncated reconstruction of the same
            # subject against this scan to compare the two on the same voxels
            out.update(psnr3d_fov=float(metrics.masked_psnr3d(vol, scan.truth, fov)),
                       ssim3d_fov=float(metrics.masked_ssim3d(vol, scan.truth, fov)),
                       fov_fraction=float(fov.mean()))
    if scan.surface is not None:
        from clgs.mesh.surface import SurfaceError

        try:
            try:
                level = surface_level(anatomy, scan.truth)
            except ValueError as exc:  # a truth with fewer than three values has no bone level
                raise SurfaceError(f"no bone level in the truth ({exc})") from None
            mesh = bone_surface(vol, scan.geometry, level)
            if mesh is None:
                raise SurfaceError(f"no bone surface: no voxel of the reconstruction is above the level {level:.4g} "
                                   "(or every voxel is)")
            sd = metrics.surface_distance(mesh, scan.surface, n_samples=20000)
            out.update({f"surface_{k}_mm": v for k, v in sd.items()}, surface_level=level)
        except SurfaceError as exc:
            out["surface_error"] = str(exc)
    return out
