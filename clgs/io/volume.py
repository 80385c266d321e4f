"""Volumes on disk: ``.npy`` (the array only) or NIfTI (``.nii``/``.nii.gz``) with a correct affine.

Our arrays are (Z, Y, X): ``volume[k, j, i]`` is the voxel whose centre, in world mm, is
``origin + (i dX, j dY, k dZ)`` with ``origin`` the centre of voxel [0, 0, 0] as (x, y, z). For a
:class:`~clgs.geometry.Geometry` that origin is ``offOrigin - (nVoxel - 1) / 2 * dVoxel`` (per axis),
i.e. the Geometry convention ``centre = offOrigin + ((i - (nX-1)/2) dX, ...)``.

NIfTI indexes its data array as (i, j, k) = (x, y, z), so the array is transposed to (X, Y, Z) on
write (and back on read), and the affine is ``diag(dX, dY, dZ)`` with translation ``origin``: a
viewer then shows the true spacing and position. The world frame is the clgs scanner frame in mm
(x, y in the rotation plane, z along the rotation axis); NIfTI readers label it RAS, clgs does not
know the patient's orientation. On read, any NIfTI is first brought to the closest axis-aligned
(RAS+) orientation with nibabel, so flipped or permuted scanner files come back as (Z, Y, X) with
positive spacings; an oblique rotation that cannot be represented is dropped with a warning.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np

from clgs.errors import ClgsError
from clgs.io import atomic

__all__ = ["VolumeError", "LoadedVolume", "save_volume", "load_volume", "volume_affine",
           "grid_spacing_origin", "VOLUME_SUFFIXES"]

VOLUME_SUFFIXES = (".npy", ".nii", ".nii.gz")


class VolumeError(ClgsError, ValueError):
    """A volume file that cannot be read or written as asked."""


class LoadedVolume(NamedTuple):
    """``volume`` (Z, Y, X); ``spacing`` (dZ, dY, dX) mm and ``origin`` (x, y, z) mm of the centre of
    voxel [0, 0, 0], both None for ``.npy`` files (which carry no geometry)."""

    volume: np.ndarray
    spacing: Optional[tuple]
    origin: Optional[tuple]


def _kind(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz") or name.endswith(".nii"):
        return "nifti"
    if name.endswith(".npy"):
        return "npy"
    raise VolumeError(f"{path}: unknown volume format; use one of {', '.join(VOLUME_SUFFIXES)}")


def grid_spacing_origin(geometry=None, spacing=None, origin=None, shape=None):
    """Resolve (spacing_zyx, origin_xyz of voxel 0) from a Geometry, a Grid, or explicit values.

    ``spacing`` defaults to 1 mm and ``origin`` to the value that centres the volume on (0, 0, 0).
    """
    if geometry is not None:
        if spacing is not None or origin is not None:
            raise ValueError("give either a geometry or spacing/origin, not both")
        if hasattr(geometry, "dVoxel"):  # Geometry
            grid = geometry.volume_grid(scene=False)
            return tuple(float(s) for s in grid.spacing[::-1]), tuple(float(o) for o in grid.origin)
        if hasattr(geometry, "spacing") and hasattr(geometry, "origin"):  # Grid (x, y, z)
            return tuple(float(s) for s in geometry.spacing[::-1]), tuple(float(o) for o in geometry.origin)
        raise TypeError(f"expected a Geometry or Grid, got {type(geometry).__name__}")
    sp = np.ones(3) if spacing is None else np.asarray(spacing, float).reshape(-1)
    if sp.size == 1:
        sp = np.repeat(sp, 3)
    if sp.size != 3 or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise VolumeError(f"spacing must be 3 positive numbers (dZ, dY, dX) in mm, got {spacing!r}")
    if origin is None:
        if shape is None:
            raise ValueError("shape is needed to centre a volume")
        org = -0.5 * (np.asarray(shape[::-1], float) - 1) * sp[::-1]
    else:
        org = np.asarray(origin, float).reshape(-1)
        if org.size != 3 or not np.all(np.isfinite(org)):
            raise VolumeError(f"origin must be 3 finite numbers (x, y, z) in mm, got {origin!r}")
    return tuple(float(s) for s in sp), tuple(float(o) for o in org)


def volume_affine(spacing_zyx, origin_xyz) -> np.ndarray:
    """4x4 NIfTI affine: voxel (i, j, k) of the (X, Y, Z)-ordered array -> world (x, y, z) mm."""
    aff = np.eye(4)
    aff[0, 0], aff[1, 1], aff[2, 2] = np.asarray(spacing_zyx, float)[::-1]
    aff[:3, 3] = np.asarray(origin_xyz, float)
    return aff


def _storage_array(volume: np.ndarray) -> np.ndarray:
    if volume.dtype == bool:
        return volume.astype(np.uint8)
    if np.issubdtype(volume.dtype, np.floating):
        return volume.astype(np.float32, copy=False)
    if np.issubdtype(volume.dtype, np.integer):
        return volume
    raise VolumeError(f"cannot store a volume of dtype {volume.dtype}")


def save_volume(path, volume, geometry=None, *, spacing=None, origin=None, overwrite: bool = True) -> Path:
    """Write a (Z, Y, X) volume to ``.npy``, ``.nii`` or ``.nii.gz`` atomically.

    Position: a :class:`~clgs.geometry.Geometry` or :class:`~clgs.geometry.Grid` (``geometry``), or
    ``spacing`` (dZ, dY, dX) mm and ``origin`` (x, y, z) mm of the centre of voxel [0, 0, 0]
    (default: 1 mm, centred). ``.npy`` keeps only the array. Floats are stored as float32,
    booleans as uint8, integers as they are.
    """
    path = Path(path)
    kind = _kind(path)
    vol = np.asarray(volume)
    if vol.ndim != 3:
        raise VolumeError(f"a volume must be 3-D (Z, Y, X), got shape {vol.shape}")
    if geometry is not None and hasattr(geometry, "nVoxel") and tuple(geometry.nVoxel) != vol.shape:
        raise VolumeError(f"volume shape {vol.shape} does not match the geometry's nVoxel {geometry.nVoxel}")
    sp, org = grid_spacing_origin(geometry, spacing, origin, vol.shape)
    data = _storage_array(vol)
    if kind == "npy":
        return atomic.save_npy(path, data, overwrite=overwrite)
    import nibabel as nib

    img = nib.Nifti1Image(np.ascontiguousarray(data.transpose(2, 1, 0)), volume_affine(sp, org))
    img.header.set_xyzt_units("mm")
    img.set_sform(img.affine, code=1)  # scanner-anatomical frame
    img.set_qform(img.affine, code=1)
    with atomic.atomic_path(path, overwrite) as tmp:
        nib.save(img, str(tmp))
    return path


def load_volume(path, dtype=np.float32) -> LoadedVolume:
    """Read a volume: ``(volume (Z, Y, X), spacing (dZ, dY, dX) or None, origin (x, y, z) or None)``.

    ``dtype=None`` keeps the stored type (e.g. integer labels). Clear errors for missing,
    unreadable or non-3-D files.
    """
    path = Path(path)
    kind = _kind(path)
    if not path.is_file():
        raise VolumeError(f"{path}: no such file")
    if kind == "npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - any failure here means an unreadable file
            raise VolumeError(f"{path}: not a readable .npy array ({exc})") from exc
        arr = _check_3d(path, arr)
        return LoadedVolume(arr if dtype is None else arr.astype(dtype, copy=False), None, None)
    import nibabel as nib

    try:
        img = nib.load(str(path))
        img = nib.as_closest_canonical(img)
        arr = np.asarray(img.dataobj)
    except Exception as exc:  # noqa: BLE001
        raise VolumeError(f"{path}: not a readable NIfTI file ({exc})") from exc
    arr = _check_3d(path, arr)
    aff = np.asarray(img.affine, float)
    lin = aff[:3, :3]
    spacing_xyz = np.sqrt((lin ** 2).sum(0))
    if np.any(spacing_xyz <= 0) or not np.all(np.isfinite(aff)):
        raise VolumeError(f"{path}: the NIfTI affine is degenerate ({aff.tolist()})")
    if not np.allclose(lin, np.diag(spacing_xyz), atol=1e-6 * spacing_xyz.max()):
        warnings.warn(f"{path}: oblique NIfTI affine; keeping spacing and origin, dropping the rotation",
                      stacklevel=2)
    vol = np.ascontiguousarray(arr.transpose(2, 1, 0))
    if dtype is not None:
        vol = vol.astype(dtype, copy=False)
    return LoadedVolume(vol, tuple(float(s) for s in spacing_xyz[::-1]), tuple(float(o) for o in aff[:3, 3]))


def _check_3d(path, arr):
    arr = np.asarray(arr)
    if arr.ndim == 4 and arr.shape[3] == 1:
        arr = arr[..., 0]
    if arr.ndim != 3:
        raise VolumeError(f"{path}: expected a 3-D volume, got an array of shape {arr.shape}")
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise VolumeError(f"{path}: not a numeric volume (dtype {arr.dtype})")
    return arr
