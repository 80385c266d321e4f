"""Volumes on disk: ``.npy`` (the array only) or NIfTI (``.nii``/``.nii.gz``) with a correct affine.

In memory our arrays are (Z, Y, X) along +z, +y, +x of the world: ``volume[k, j, i]`` is the
voxel whose centre, in world mm, is ``origin + (i dX, j dY, k dZ)`` with ``origin`` the centre of
voxel [0, 0, 0] as (x, y, z). For a :class:`~clgs.geometry.Geometry` that origin is
``centre_xyz - (nVoxel - 1) / 2 * dVoxel`` (per axis; centre_xyz is the isocentre plus TIGRE's
``offOrigin``). The world frame is the input's (a NIfTI's scanner frame, x, y, z in mm); NIfTI
readers label it RAS, so in nibabel's axis codes the working array ``volume.T`` is ``"RAS"``.

Files keep the order of the input (:mod:`clgs.io.orientation`). On read, any NIfTI, MetaImage,
NRRD or DICOM series is brought to the working order with nibabel (flips and axis swaps, no
interpolation), and :class:`LoadedVolume` says the file's axis codes (``orientation``: ``"LAS"``
for dcm2niix's usual output, ``"LPS"`` for an axial DICOM series, ``"PSR"`` for a permuted file).
On write, ``save_volume(path, volume, geometry)`` puts the array back in the order of
``geometry.orientation`` (or ``orientation=``) with the matching affine: a NIfTI stored ``"LAS"``
with affine ``diag(-2.5, 2.5, 2.5)`` comes back from a simulation and a reconstruction as
``"LAS"`` with that same affine, so arrays compare with the input index by index, and every voxel
lies where it lay. A ``.npy`` holds what the NIfTI holds, its axes reversed to (k, j, i) (for
``"RAS"`` that is the working (Z, Y, X) array). An oblique volume (its axes not along x, y, z)
is resampled onto an axis-aligned ``"RAS"`` grid of the same spacing that holds it whole
(trilinear, zero outside), with a warning; that grid is then the input, and outputs keep it.

Units: with ``units=`` ("1/mm" or "HU" at ``kev``), a NIfTI says them in its header
(``descrip``, a sentence, and ``intent_name``, e.g. ``mu 1/mm`` or ``HU 70 keV``); MetaImage and
NRRD in the fields ``clgs_units`` (and ``clgs_kev``). A ``.npy`` carries none (a run's
``report.json`` and a scan's ``scan.json`` say them).

MetaImage (``.mha``/``.mhd``), NRRD (``.nrrd``/``.nhdr``) and DICOM series (a folder of slices,
or one ``.dcm`` file of the series) are read and written through SimpleITK (the ``formats``
extra, which the set-up installs). ITK's world frame is LPS: x and y are negated on the way in
and out, so a volume read from DICOM and written as NIfTI lies where it lay, in any viewer.
Integer volumes keep their type where the format has it; ``int64`` / ``uint64`` (which NIfTI
does not take) are stored as the narrowest integer type that holds their values.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from clgs.errors import ClgsError, InputError
from clgs.geometry import GeometryError, check_orientation
from clgs.io import atomic
from clgs.io.dicom_series import series_in, several_series_message, slice_gap, slice_thickness
from clgs.io.orientation import WORKING, axis_codes, file_affine, to_file

__all__ = ["VolumeError", "LoadedVolume", "save_volume", "load_volume", "volume_affine",
           "grid_spacing_origin", "VOLUME_SUFFIXES"]

from clgs.io.suffixes import ITK_SUFFIXES, VOLUME_SUFFIXES  # noqa: E402

LPS = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS (its own inverse)


class VolumeError(ClgsError, ValueError):
    """A volume file that cannot be read or written as asked."""


class _Loaded(NamedTuple):
    volume: np.ndarray
    spacing: tuple | None
    origin: tuple | None


class LoadedVolume(_Loaded):
    """``volume`` (Z, Y, X) in the working order; ``spacing`` (dZ, dY, dX) mm and ``origin`` (x, y, z)
    mm of the centre of voxel [0, 0, 0], both None for ``.npy`` files (which carry no geometry).
    Unpacks as those three; ``orientation`` (an attribute) holds the file's axis codes (``"RAS"`` for
    ``.npy`` files and resampled oblique volumes), what ``save_volume`` takes to write it back."""

    orientation: str = WORKING

    def __new__(cls, volume, spacing, origin, orientation: str = WORKING):
        self = super().__new__(cls, volume, spacing, origin)
        self.orientation = orientation
        return self


def _kind(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".nii.gz") or name.endswith(".nii"):
        return "nifti"
    if name.endswith(".npy"):
        return "npy"
    if name.endswith(ITK_SUFFIXES):
        return "itk"
    if name.endswith(".dcm") or path.is_dir():
        return "dicom"
    raise VolumeError(f"{path}: unknown volume format; use one of {', '.join(VOLUME_SUFFIXES)}")


def grid_spacing_origin(geometry=None, spacing=None, origin=None, shape=None):
    """Resolve (spacing_zyx, origin_xyz of voxel 0) from a Geometry, a Grid, or explicit values.

    ``spacing`` defaults to 1 mm and ``origin`` to the value that centres the volume on (0, 0, 0).
    """
    if geometry is not None:
        if spacing is not None or origin is not None:
            raise InputError("give either a geometry or spacing/origin, not both")
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
            raise InputError("shape is needed to centre a volume")
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
        if volume.dtype.itemsize < 8:
            return volume
        lo, hi = (int(volume.min()), int(volume.max())) if volume.size else (0, 0)
        for t in (np.uint8, np.int16, np.int32):
            if np.iinfo(t).min <= lo and hi <= np.iinfo(t).max:
                return volume.astype(t)
        raise VolumeError(f"integer values from {lo} to {hi} do not fit in 32 bits; convert the volume to float")
    raise VolumeError(f"cannot store a volume of dtype {volume.dtype} (complex or non-numeric); "
                      "give real attenuation values or integer labels")


def save_volume(path, volume, geometry=None, *, spacing=None, origin=None, orientation: str | None = None,
                units: str | None = None, kev: float | None = None, overwrite: bool = True) -> Path:
    """Write a (Z, Y, X) working-order volume to ``.npy``, NIfTI, MetaImage or NRRD atomically.

    Position: a :class:`~clgs.geometry.Geometry` or :class:`~clgs.geometry.Grid` (``geometry``), or
    ``spacing`` (dZ, dY, dX) mm and ``origin`` (x, y, z) mm of the centre of voxel [0, 0, 0]
    (default: 1 mm, centred). Array order in the file: ``orientation`` (axis codes, e.g. ``"LAS"``),
    by default the geometry's (the input's), else ``"RAS"``. ``units``: ``"1/mm"`` or ``"HU"`` (with
    ``kev``), written into the header; None for labels and masks. ``.npy`` keeps only the array
    (in the file's order, axes reversed). Floats are stored as float32, booleans as uint8,
    integers as they are.
    """
    path = Path(path)
    kind = _kind(path)
    vol = np.asarray(volume)
    if vol.ndim != 3:
        raise VolumeError(f"a volume must be 3-D (Z, Y, X), got shape {vol.shape}")
    if geometry is not None and hasattr(geometry, "nVoxel") and tuple(geometry.nVoxel) != vol.shape:
        raise VolumeError(f"volume shape {vol.shape} does not match the geometry's nVoxel {geometry.nVoxel}")
    sp, org = grid_spacing_origin(geometry, spacing, origin, vol.shape)
    try:
        codes = check_orientation(orientation if orientation is not None else
                                  getattr(geometry, "orientation", WORKING))
    except GeometryError as exc:
        raise VolumeError(str(exc)) from None
    notes = None
    if units is not None:
        from clgs.io.units import header_text, units_record

        notes = (units_record(units, kev), header_text(units, kev))
    data = to_file(_storage_array(vol), codes)  # (k, j, i) of the file
    aff = file_affine(sp, org, vol.shape, codes)
    if kind == "npy":
        return atomic.save_npy(path, data, overwrite=overwrite)
    if kind in ("itk", "dicom"):
        if kind == "dicom":
            raise VolumeError(f"{path}: a DICOM series is a folder of slices: write it with "
                              "`clgs convert VOLUME FOLDER --dicom` (or clgs.io.dicom.save_dicom_series); "
                              "here write .nii.gz, .nrrd or .mha")
        sitk = require_simpleitk()
        img = sitk.GetImageFromArray(np.ascontiguousarray(data))
        step = np.sqrt((aff[:3, :3] ** 2).sum(0))  # the file's (i, j, k) voxel sizes
        img.SetSpacing(tuple(float(v) for v in step))
        img.SetOrigin(tuple(float(v) for v in aff[:3, 3] * LPS))
        img.SetDirection(tuple(float(v) for v in ((aff[:3, :3] / step) * LPS[:, None]).reshape(-1)))
        if notes is not None:
            img.SetMetaData("clgs_units", notes[0]["units"])
            if "kev" in notes[0]:
                img.SetMetaData("clgs_kev", f"{notes[0]['kev']:g}")
        return _write_itk(sitk, img, path, overwrite)
    import nibabel as nib

    img = nib.Nifti1Image(np.ascontiguousarray(data.T), aff)
    img.header.set_xyzt_units("mm")
    if notes is not None:
        img.header["descrip"] = notes[1][0].encode("ascii")[:80]
        img.header["intent_name"] = notes[1][1].encode("ascii")[:16]
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
    if not path.exists():
        raise VolumeError(f"{path}: no such file")
    if kind in ("itk", "dicom"):
        arr_xyz, aff = _read_itk(path, kind)
        return _from_affine(path, arr_xyz, aff, dtype)
    if kind == "npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - any failure here means an unreadable file
            raise VolumeError(f"{path}: not a readable .npy array ({exc})") from exc
        arr = _check_3d(path, arr)
        return LoadedVolume(arr if dtype is None else arr.astype(dtype, copy=False), None, None)
    import nibabel as nib

    _check_nifti_voxel_size(path)
    try:
        img = nib.load(str(path))
        arr = np.asarray(img.dataobj)
    except Exception as exc:  # noqa: BLE001
        raise VolumeError(f"{path}: not a readable NIfTI file ({exc})") from exc
    return _from_affine(path, arr, np.asarray(img.affine, float), dtype)


def _check_nifti_voxel_size(path: Path) -> None:
    """Refuse a NIfTI placed by voxel sizes alone (no sform, no qform) with a size of 0: nibabel
    would quietly make it 1 mm, and every distance in the reconstruction would be wrong."""
    import gzip

    import nibabel as nib

    try:
        opener = gzip.open if path.name.lower().endswith(".gz") else open
        with opener(path, "rb") as fh:
            hdr = nib.Nifti1Header.from_fileobj(fh, check=False)
        pixdim = np.asarray(hdr["pixdim"][1:4], float)
        placed = int(hdr["sform_code"]) > 0 or int(hdr["qform_code"]) > 0
    except Exception:  # noqa: BLE001 - an unreadable header is reported by the full read
        return
    if not placed and (np.any(pixdim <= 0) or not np.all(np.isfinite(pixdim))):
        raise VolumeError(f"{path}: voxel size {pixdim.tolist()} mm (zero, negative or not a number) and no "
                          "orientation matrix; fix the header's pixdim (the voxel size in mm)")


def _write_itk(sitk, img, path: Path, overwrite: bool) -> Path:
    """Write ``img`` with ITK under ``path``. The file is made in a temporary folder beside it under
    its final name (ITK picks the writer by suffix, and a detached header names its data file), then
    moved in: data files first, the header last, so a reader never finds a header without data."""
    import shutil
    import tempfile

    if not overwrite and path.exists():
        raise FileExistsError(f"{path} already exists")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmpdir = Path(tempfile.mkdtemp(prefix=".clgs-tmp-", dir=path.parent))
    try:
        sitk.WriteImage(img, str(tmpdir / path.name), True)
        made = sorted(tmpdir.iterdir(), key=lambda f: f.name == path.name)
        for f in made:
            os.replace(f, path.parent / f.name)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return path


def require_simpleitk():
    """SimpleITK, or an error that says how to install it (DICOM, MetaImage and NRRD need it)."""
    try:
        import SimpleITK as sitk
    except ImportError as exc:
        raise VolumeError("reading and writing DICOM, MetaImage and NRRD needs SimpleITK: "
                          "pip install 'clgs[formats]' (the set-up installs it)") from exc
    return sitk


def _read_itk(path: Path, kind: str):
    """(array indexed (x, y, z), 4x4 RAS affine) of an ITK-readable file or DICOM series."""
    sitk = require_simpleitk()
    try:
        if kind == "dicom":
            folder = path if path.is_dir() else path.parent
            reader = sitk.ImageSeriesReader()
            series = reader.GetGDCMSeriesIDs(str(folder))
            if not series:
                raise VolumeError(f"{folder}: no DICOM series found")
            if len(series) > 1 and path.is_dir():
                named = series_in(folder)
                raise VolumeError(several_series_message(folder, named) if len(named) > 1 else
                                  f"{folder}: holds {len(series)} DICOM series; name one of its files instead")
            sid = series[0]
            if not path.is_dir():
                sid = next((s for s in series if str(path) in reader.GetGDCMSeriesFileNames(str(folder), s)),
                           series[0])
            files = reader.GetGDCMSeriesFileNames(str(folder), sid)
            reader.SetFileNames(files)
            img = reader.Execute()
            _dicom_spacing(folder, files, img)
        else:
            img = sitk.ReadImage(str(path))
    except VolumeError:
        raise
    except Exception as exc:  # noqa: BLE001 - ITK's own message says what it could not read
        raise VolumeError(f"{path}: not a readable volume ({str(exc).strip().splitlines()[-1]})") from exc
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise VolumeError(f"{path}: expected a 3-D scalar volume, got {img.GetDimension()}-D with "
                          f"{img.GetNumberOfComponentsPerPixel()} components per voxel")
    arr = sitk.GetArrayFromImage(img)  # (z, y, x)
    direction = np.asarray(img.GetDirection(), float).reshape(3, 3) * LPS[:, None]  # rows in RAS
    aff = np.eye(4)
    aff[:3, :3] = direction * np.asarray(img.GetSpacing(), float)[None, :]
    aff[:3, 3] = np.asarray(img.GetOrigin(), float) * LPS
    return np.ascontiguousarray(arr.transpose(2, 1, 0)), aff


def _dicom_spacing(folder, files, img) -> None:
    """Warn where the series' slices are unevenly spaced (ITK spaces them evenly); give a single
    slice its SliceThickness as the slice spacing (ITK gives it 1 mm)."""
    if len(files) == 1:
        thickness = slice_thickness(files[0])
        if thickness is not None:
            img.SetSpacing(tuple(img.GetSpacing()[:2]) + (thickness,))
        return
    gap = slice_gap(files)
    if gap:
        warnings.warn(f"{folder}: {gap}", stacklevel=4)


def _from_affine(path, arr, aff, dtype) -> LoadedVolume:
    """A volume indexed (i, j, k) with a voxel-to-world (RAS, mm) affine, as clgs's (Z, Y, X) array
    with spacing, origin and the file's axis codes: brought to the working (RAS+) order; an oblique
    one resampled onto an axis-aligned grid (with a warning), whose codes are then ``"RAS"``."""
    import nibabel as nib

    arr = _check_3d(path, arr)
    if not np.all(np.isfinite(aff)) or abs(np.linalg.det(aff[:3, :3])) < 1e-12:
        raise VolumeError(f"{path}: the voxel-to-world matrix is degenerate ({aff.tolist()}); "
                          "a zero voxel size cannot be placed in the world")
    codes = axis_codes(aff)
    img = nib.as_closest_canonical(nib.Nifti1Image(arr, aff))
    arr = np.asarray(img.dataobj)
    aff = np.asarray(img.affine, float)
    lin = aff[:3, :3]
    spacing_xyz = np.sqrt((lin ** 2).sum(0))
    if np.any(spacing_xyz <= 0):
        raise VolumeError(f"{path}: a voxel size is zero ({spacing_xyz.tolist()} mm); fix the file's header")
    if not np.allclose(lin, np.diag(spacing_xyz), atol=1e-6 * spacing_xyz.max()):
        arr, aff = _axis_aligned(arr, aff, spacing_xyz)
        codes = WORKING  # the resampled grid is the input from here on
        warnings.warn(f"{path}: oblique volume (axes not along x, y, z); resampled onto an axis-aligned grid "
                      f"of {arr.shape[0]} x {arr.shape[1]} x {arr.shape[2]} voxels of "
                      f"{' x '.join(f'{v:g}' for v in spacing_xyz)} mm that holds it whole", stacklevel=3)
    vol = np.ascontiguousarray(arr.transpose(2, 1, 0))
    if dtype is not None:
        vol = vol.astype(dtype, copy=False)
    return LoadedVolume(vol, tuple(float(s) for s in spacing_xyz[::-1]), tuple(float(o) for o in aff[:3, 3]), codes)


def _axis_aligned(arr, aff, spacing_xyz):
    """Resample an oblique volume (indexed (i, j, k), affine ``aff``) onto the axis-aligned grid of
    spacing ``spacing_xyz`` that covers its corners: trilinear, zero outside the input."""
    from scipy import ndimage

    n = np.asarray(arr.shape, float)
    corners = np.array([[i, j, k, 1.0] for i in (0, n[0] - 1) for j in (0, n[1] - 1) for k in (0, n[2] - 1)])
    world = corners @ aff.T
    lo, hi = world[:, :3].min(0), world[:, :3].max(0)
    shape = tuple(int(v) for v in np.floor((hi - lo) / spacing_xyz + 1e-6) + 1)
    new = np.eye(4)
    new[:3, :3] = np.diag(spacing_xyz)
    new[:3, 3] = lo
    to_input = np.linalg.inv(aff) @ new  # output index -> input index
    labels = np.issubdtype(arr.dtype, np.integer) or arr.dtype == bool  # labels: nearest, never blended
    data = np.asarray(arr, dtype=arr.dtype if labels else np.float64)
    out = ndimage.affine_transform(data, to_input[:3, :3], offset=to_input[:3, 3], output_shape=shape,
                                   order=0 if labels else 1, mode="constant", cval=0)
    return out, new


def _check_3d(path, arr):
    arr = np.asarray(arr)
    if arr.ndim == 4 and arr.shape[3] == 1:
        arr = arr[..., 0]
    if arr.ndim != 3:
        raise VolumeError(f"{path}: expected a 3-D volume, got an array of shape {arr.shape}")
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise VolumeError(f"{path}: not a numeric volume (dtype {arr.dtype})")
    return arr
