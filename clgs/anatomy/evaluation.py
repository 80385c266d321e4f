"""Evaluation of a reconstruction against a simulated scan's truth: the solid bone mask, its outer
surface (written to a run folder as ``surface.stl`` with ``surface.json`` naming the level and its
source; :mod:`clgs.anatomy.bone_level` says where levels come from) and the metrics (PSNR, SSIM,
surface distance of that same surface). Library code shared by ``clgs <anatomy> ...``,
:mod:`clgs.experiment` and :mod:`clgs.methods.shape_guided`."""
from __future__ import annotations

from pathlib import Path

from clgs.anatomy.bone_level import BoneLevel, choose_level
from clgs.errors import InputError
from clgs.progress import phased

__all__ = ["surface_level", "bone_mask", "solid_bone", "bone_surface", "bone_surface_closed", "write_bone_surface",
           "read_bone_surface", "evaluate_volume", "truncated_field_of_view", "SURFACE_FILE", "SURFACE_RECORD",
           "LEVEL_KEYS"]

#: what a surface's record says of how it was taken (a method's info and a report carry these on)
LEVEL_KEYS = ("surface_level", "surface_level_source", "surface_closing_max_voxels", "surface_closing_voxels")
#: the bone surface of a run folder, and the record of the level it was taken at
SURFACE_FILE = "surface.stl"
SURFACE_RECORD = "surface.json"


def surface_level(anatomy, truth) -> float:
    """The bone iso-level for evaluating against ``truth``: :func:`clgs.anatomy.bone_level.choose_level`
    (the anatomy's scene level, else the truth's); a ValueError when neither gives one."""
    level = choose_level(anatomy=anatomy, truth=truth)
    if level is None:
        raise ValueError("no bone level: the anatomy names none and the truth has no bone class")
    return level.value


def bone_mask(volume, level: float, min_piece: float = 0.1, closing: int = 0):
    """The solid bone: voxels above ``level``, pieces smaller than ``min_piece`` x the largest
    dropped, gaps in the bone's wall sealed (``closing``, below), enclosed cavities (medullary
    canal, cancellous interior below the level) filled; so the surface compared is the outer bone
    surface, not every iso-contour or speck. (A sparse-view reconstruction often breaks a bone at
    thin cortex: keeping only the largest piece would measure one fragment's surface against the
    whole bone.)

    ``closing`` (voxels, the anatomy's ``scene.surface_closing``): a sparse-view reconstruction
    also opens holes in a thin cortex, through which the marrow cavity and the cancellous ends
    reach the outside and are not filled: their walls would be written as bone surface (a femur
    from 10 views: a fifth of its surface inside the bone). A morphological closing by a ball
    seals them, at the largest radius from 1 to ``closing`` whose step from the one before grew
    the solid bone by more than :data:`CLOSING_GROWTH` (a sealed cavity; past it only the outer
    creases fill); 0: none, for anatomies of several bones, which a closing could join.
    :func:`solid_bone` also returns the radius used."""
    return solid_bone(volume, level, min_piece, closing)[0]


#: a closing's step (one voxel more) that grows the solid bone by more than this share sealed a hole
CLOSING_GROWTH = 0.01


def solid_bone(volume, level: float, min_piece: float = 0.1, closing: int = 0) -> tuple:
    """(:func:`bone_mask`'s mask, the closing radius it used, voxels; 0 for none).

    Every radius from 1 to ``closing`` is tried; the one used is the largest whose step from the
    radius before grew the solid bone by more than :data:`CLOSING_GROWTH` (a hole sealed), so a
    hole that only a ball of 3 seals is sealed even where a ball of 1 or 2 changes nothing."""
    import numpy as np
    from scipy import ndimage

    mask = np.asarray(volume) > level
    labels, n = ndimage.label(mask)
    if n > 1:
        sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, n + 1))
        keep = np.flatnonzero(sizes >= min_piece * sizes.max()) + 1
        mask = np.isin(labels, keep)
    solid, radius = ndimage.binary_fill_holes(mask), 0
    if closing and solid.any():
        sizes = [int(solid.sum())]
        closed = [solid]
        for c in _closings(mask, int(closing)):
            closed.append(ndimage.binary_fill_holes(c))
            sizes.append(int(closed[-1].sum()))
        grew = [r for r in range(1, len(sizes)) if sizes[r] - sizes[r - 1] > CLOSING_GROWTH * sizes[r - 1]]
        if grew:
            radius = grew[-1]
            solid = closed[radius]
    return solid, radius


def _closings(mask, largest: int):
    """The closings of ``mask`` by a ball of 1, 2, ... ``largest`` voxels (a generator), as
    scipy's ``binary_closing`` with that ball would give on the mask padded with empty voxels (so
    bone at the grid's edge is not eroded from outside it; ``tests/test_evaluation.py`` checks the
    two agree). Made from Euclidean distance transforms on the bone's bounding box, where
    ``binary_closing`` passes over the grid once per voxel of the ball (123 for a ball of 3); all
    three radii and their fills take 3.3 s at 256^3 (docs/outputs.md). A ball, not the
    6-neighbour cross iterated: the cross's corner reaches deep into a hole and keeps it open (3
    voxels wide through a wall of 4 stays open at any radius; a ball of 3 seals it)."""
    import numpy as np
    from scipy import ndimage

    pad = largest + 1
    where = np.argwhere(mask)
    lo, hi = where.min(0), where.max(0) + 1
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    crop = np.pad(mask[box], pad)
    to_bone = ndimage.distance_transform_edt(~crop)  # each voxel's distance to the nearest bone voxel
    inner = tuple(slice(pad, pad + (b - a)) for a, b in zip(lo, hi))
    for r in range(1, largest + 1):
        dilated = to_bone <= r
        closed = ndimage.distance_transform_edt(dilated) > r  # eroded: no voxel outside within r
        out = np.zeros_like(mask)
        out[box] = closed[inner]
        yield out


def bone_surface(volume, geometry, level):
    """The outer bone surface (:class:`clgs.io.mesh.Mesh`, mm) of a (Z, Y, X) volume on
    ``geometry``'s grid: :func:`clgs.mesh.surface.surface_from_volume` of :func:`bone_mask` at
    ``level`` (1/mm, or a :class:`clgs.anatomy.bone_level.BoneLevel`, whose closing it uses; see
    that module for where a level comes from). None when no surface separates bone from the rest
    (nothing, or everything, above the level)."""
    found = bone_surface_closed(volume, geometry, level)
    return None if found is None else found[0]


def bone_surface_closed(volume, geometry, level):
    """(:func:`bone_surface`'s mesh, the closing radius it used in voxels) or None."""
    import numpy as np

    from clgs.mesh.surface import surface_from_volume

    closing = 0
    if isinstance(level, BoneLevel):
        level, closing = level.value, level.closing
    if level is None:
        raise TypeError("bone_surface needs the bone level (clgs.anatomy.bone_level.choose_level gives one)")
    vol = np.asarray(volume, np.float32)
    mask, radius = solid_bone(vol, float(level), closing=closing)
    if not mask.any() or mask.all():
        return None
    return surface_from_volume(mask, geometry=geometry), radius


@phased("the bone surface")
def write_bone_surface(out_dir, volume, geometry, level: BoneLevel | None) -> dict:
    """Write ``out_dir/surface.stl`` (the bone surface of ``volume`` at ``level``) and
    ``out_dir/surface.json`` (the level, its source, the file); returns that record plus ``path``
    (None when nothing was written: no level, or no bone above it, and then ``reason``). A stale
    surface of an earlier run in the folder is removed, so the folder never holds a surface that is
    not its volume's."""
    from clgs.io import atomic
    from clgs.io.mesh import save_mesh

    out_dir = Path(out_dir)
    found = None if level is None else bone_surface_closed(volume, geometry, level)
    if found is None:
        for name in (SURFACE_FILE, SURFACE_RECORD):
            (out_dir / name).unlink(missing_ok=True)
        reason = ("no bone level: give one with --surface-level (Python: surface_level=)" if level is None else
                  f"no voxel of the volume is above the bone level {level.value:.4g} (or every voxel is)")
        return {"path": None, "reason": reason, **({} if level is None else level.record())}
    mesh, radius = found
    path = save_mesh(out_dir / SURFACE_FILE, mesh.vertices, mesh.faces)
    sealed = f", gaps in its wall sealed by a {radius}-voxel closing" if radius else ""
    record = {"surface": SURFACE_FILE, "what": "the outer bone surface of the volume (world mm): solid bone above "
              f"the level{sealed}, cavities filled, specks dropped", **level.record(),
              **({"surface_closing_voxels": radius} if level.closing else {})}
    atomic.write_json(out_dir / SURFACE_RECORD, record)
    return {**record, "path": str(path)}


def read_bone_surface(folder):
    """(mesh, :class:`BoneLevel`) of a run folder's ``surface.stl`` and ``surface.json``, read back
    from disk; None when the folder holds no such pair."""
    import json

    from clgs.io.mesh import load_mesh

    folder = Path(folder)
    if not ((folder / SURFACE_FILE).is_file() and (folder / SURFACE_RECORD).is_file()):
        return None
    record = json.loads((folder / SURFACE_RECORD).read_text(encoding="utf-8"))
    level = BoneLevel(float(record["surface_level"]), str(record["surface_level_source"]),
                      int(record.get("surface_closing_max_voxels", 0)))
    return load_mesh(folder / SURFACE_FILE), level


def truncated_field_of_view(scan):
    """(Z, Y, X) bool of :meth:`clgs.geometry.Geometry.field_of_view` for a scan simulated with a
    smaller detector (``meta['acquisition']['detector_fov_mm']``); None for any other scan."""
    acq = (scan.meta or {}).get("acquisition") or {}
    if not acq.get("detector_fov_mm"):
        return None
    return scan.geometry.field_of_view()


@phased("measuring the volume against the truth")
def evaluate_volume(anatomy, scan, volume, surface=None, level: BoneLevel | None = None) -> dict:
    """PSNR/SSIM against the scan's truth and, when the scan has the true surface, the surface
    distance (mm) from the reconstruction's outer bone surface to it, with the level
    (``surface_level``) and its source (``surface_level_source``).

    ``surface``: the bone surface to measure (the one a run wrote, read back: then ``level`` is
    the level it was written at); without it the surface is taken from ``volume`` at ``level``,
    or at :func:`clgs.anatomy.bone_level.choose_level`'s level for this anatomy and scan."""
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
            if level is None:
                level = choose_level(anatomy=anatomy, truth=scan.truth, scan_meta=scan.meta)
            if level is None:
                raise SurfaceError("no bone level: the anatomy names none and the truth has no bone class")
            mesh = surface if surface is not None else bone_surface(vol, scan.geometry, level)
            if mesh is None:
                raise SurfaceError(f"no bone surface: no voxel of the reconstruction is above the level "
                                   f"{level.value:.4g} (or every voxel is)")
            sd = metrics.surface_distance(mesh, scan.surface, n_samples=20000)
            out.update({f"surface_{k}_mm": v for k, v in sd.items()}, **level.record())
        except SurfaceError as exc:
            out["surface_error"] = str(exc)
            if level is not None:
                out.update(level.record())
    return out
