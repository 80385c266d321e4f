"""Volumes out as a DICOM CT series (CT Image Storage), one file per slice, as a scanner writes it.

* Values: Hounsfield units in signed 16-bit integers (rescale slope 1, intercept 0, type HU);
  attenuation (1/mm) is converted at a stated X-ray energy (:mod:`clgs.io.units`) and rounded to
  the nearest HU (at most 0.5 HU off; values beyond the int16 range are clipped and counted).
* Place: DICOM's patient frame is LPS. Slices are axial with ``ImageOrientationPatient``
  ``1\\0\\0\\0\\1\\0`` (rows along +x of LPS, the patient's left; columns along +y, posterior), in
  ascending z, each with the ``ImagePositionPatient`` of its first pixel. clgs's volumes run along
  +x and +y of RAS, so each slice is flipped in both axes on the way out: every voxel lies at the
  same world point as in clgs's NIfTI files.
* Who: patient, study and frame of reference from an identity (:mod:`clgs.io.dicom_identity`):
  a scan's (one study and one frame of reference for all its reconstructions, each a series), the
  DICOM input's it came from, or an anonymous one derived from the volume.
* Display: two windows, the first from the data (its 0.5th to 99.5th percentile of HU, what a
  viewer opens with) and a bone window (centre 400, width 1800 HU).
* Determinism: UIDs, dates and every byte derive from the data, the identity and the options,
  never from the clock: the same volume gives the same files.

Written with pydicom (the ``formats`` extra); read back by :func:`clgs.io.volume.load_volume`.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from clgs.errors import ClgsError
from clgs.io import atomic
from clgs.io.dicom_identity import anonymous_identity, derived_uid
from clgs.io.units import DEFAULT_KEV, mu_to_hu

__all__ = ["DicomError", "save_dicom_series", "volume_digest", "BONE_WINDOW", "CT_IMAGE_STORAGE"]

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
EXPLICIT_VR_LITTLE_ENDIAN = "1.2.840.10008.1.2.1"
#: (centre, width) HU of the bone window
BONE_WINDOW = (400.0, 1800.0)


class DicomError(ClgsError, ValueError):
    """A volume that cannot be written as a DICOM series."""


def _require_pydicom():
    try:
        import pydicom
    except ImportError as exc:
        raise DicomError("writing a DICOM series needs pydicom: pip install 'clgs[formats]' "
                         "(the set-up installs it)") from exc
    return pydicom


def volume_digest(hu16: np.ndarray, spacing_zyx, origin_xyz) -> str:
    """SHA-256 (hex) of the stored values and their grid."""
    h = hashlib.sha256()
    h.update(str(hu16.shape).encode())
    h.update(np.ascontiguousarray(hu16).tobytes())
    h.update(np.asarray(spacing_zyx, np.float64).tobytes())
    h.update(np.asarray(origin_xyz, np.float64).tobytes())
    return h.hexdigest()


def _ds(v: float) -> str:
    """A decimal string (DS, at most 16 characters) that reads back as ``v`` to 1e-6 mm."""
    text = f"{float(v):.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text[:16]


def _windows(hu16: np.ndarray) -> tuple:
    lo, hi = (float(v) for v in np.percentile(hu16, [0.5, 99.5]))
    centre, width = round((lo + hi) / 2), max(1, round(hi - lo))
    return [_ds(centre), _ds(BONE_WINDOW[0])], [_ds(width), _ds(BONE_WINDOW[1])], ["DATA", "BONE"]


def save_dicom_series(folder, volume, spacing_zyx, origin_xyz, *, kev: float = DEFAULT_KEV,
                      identity: dict | None = None, description: str = "clgs volume", series_number: int = 1,
                      derivation: str = "", overwrite: bool = False) -> dict:
    """Write ``volume`` (Z, Y, X attenuation in 1/mm; voxel [0, 0, 0] centred at ``origin_xyz``,
    RAS mm) as a DICOM CT series in ``folder`` (made atomically).

    ``identity``: patient, study and frame-of-reference attributes (DICOM keywords, e.g. from
    :func:`clgs.io.dicom_identity.scan_identity`); default an anonymous one derived from the
    volume. ``description`` and ``series_number`` name the series within its study;
    ``derivation`` says how the volume was made. Returns a report: folder, files, keV, HU range,
    clipped voxel count, the study, series and frame-of-reference UIDs.
    """
    pydicom = _require_pydicom()
    from pydicom.dataset import Dataset, FileMetaDataset

    vol = np.asarray(volume, np.float64)
    if vol.ndim != 3:
        raise DicomError(f"a DICOM series needs a 3-D volume, got shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise DicomError("the volume holds NaN or Inf: DICOM stores integers; clean the volume first")
    sp = np.asarray(spacing_zyx, float)
    org = np.asarray(origin_xyz, float)
    hu = np.rint(mu_to_hu(vol, kev))
    clipped = int(np.count_nonzero((hu < -32768) | (hu > 32767)))
    hu16 = np.clip(hu, -32768, 32767).astype(np.int16)
    digest = volume_digest(hu16, sp, org)
    ident = dict(anonymous_identity(digest))
    ident.update(identity or {})
    series_uid = derived_uid("series", ident["StudyInstanceUID"], digest, f"{float(kev):.6g}", description,
                             int(series_number))
    nz, ny, nx = hu16.shape
    # first pixel of each slice: the voxel at the largest x and y of RAS (rows run towards -x RAS)
    first_lps = np.array([-(org[0] + (nx - 1) * sp[2]), -(org[1] + (ny - 1) * sp[1]), org[2]])
    centres, widths, names = _windows(hu16)
    version = __import__("clgs").__version__

    base = Dataset()
    base.SpecificCharacterSet = "ISO_IR 192"
    # Patient, General Study, Frame of Reference (identity)
    for key in ("PatientName", "PatientID", "IssuerOfPatientID", "PatientBirthDate", "PatientSex", "PatientAge",
                "PatientIdentityRemoved", "DeidentificationMethod", "StudyInstanceUID", "StudyDate", "StudyTime",
                "StudyID", "AccessionNumber", "ReferringPhysicianName", "StudyDescription", "FrameOfReferenceUID",
                "PositionReferenceIndicator"):
        if key in ident:
            setattr(base, key, ident[key])
    # General Series
    base.Modality = "CT"
    base.SeriesInstanceUID = series_uid
    base.SeriesNumber = int(series_number)
    base.SeriesDescription = description[:64]
    base.SeriesDate, base.SeriesTime = ident.get("StudyDate", ""), ident.get("StudyTime", "")
    base.PatientPosition = ident.get("PatientPosition", "")
    # General Equipment
    base.Manufacturer = "clgs"
    base.ManufacturerModelName = "clgs"
    base.SoftwareVersions = version
    # General Image, CT Image, Image Pixel
    base.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
    base.ContentDate, base.ContentTime = ident.get("StudyDate", ""), ident.get("StudyTime", "")
    base.AcquisitionNumber = 1
    base.KVP = ""  # the energy is monochromatic (below), not a tube voltage
    if derivation:
        base.DerivationDescription = derivation[:1024]
    base.ImageComments = f"Hounsfield units from attenuation at {float(kev):g} keV"
    base.SamplesPerPixel = 1
    base.PhotometricInterpretation = "MONOCHROME2"
    base.Rows, base.Columns = ny, nx
    base.BitsAllocated, base.BitsStored, base.HighBit, base.PixelRepresentation = 16, 16, 15, 1
    base.RescaleIntercept, base.RescaleSlope, base.RescaleType = "0", "1", "HU"
    base.WindowCenter, base.WindowWidth, base.WindowCenterWidthExplanation = centres, widths, names
    # Image Plane
    base.PixelSpacing = [_ds(sp[1]), _ds(sp[2])]  # row spacing (between rows: y), column spacing (x)
    base.ImageOrientationPatient = ["1", "0", "0", "0", "1", "0"]
    base.SliceThickness = _ds(sp[0])
    base.SOPClassUID = CT_IMAGE_STORAGE

    folder = Path(folder)
    with atomic.atomic_dir(folder, overwrite=overwrite) as tmp:
        for k in range(nz):
            ds = Dataset()
            ds.update(base)
            sop = derived_uid(series_uid, "instance", k)
            ds.SOPInstanceUID = sop
            ds.InstanceNumber = k + 1
            z = org[2] + k * sp[0]
            ds.ImagePositionPatient = [_ds(first_lps[0]), _ds(first_lps[1]), _ds(z)]
            ds.SliceLocation = _ds(z)
            ds.PixelData = np.ascontiguousarray(hu16[k, ::-1, ::-1]).astype("<i2").tobytes()
            meta = FileMetaDataset()
            meta.MediaStorageSOPClassUID = CT_IMAGE_STORAGE
            meta.MediaStorageSOPInstanceUID = sop
            meta.TransferSyntaxUID = EXPLICIT_VR_LITTLE_ENDIAN
            meta.ImplementationClassUID = derived_uid("clgs implementation", version)
            meta.ImplementationVersionName = f"CLGS_{version}"[:16]
            ds.file_meta = meta
            ds.preamble = b"\0" * 128
            pydicom.dcmwrite(tmp / f"slice{k + 1:04d}.dcm", ds, enforce_file_format=True)
    return {"folder": str(folder), "files": int(nz), "kev": float(kev), "hu_min": int(hu16.min()),
            "hu_max": int(hu16.max()), "clipped": clipped, "study_uid": ident["StudyInstanceUID"],
            "series_uid": series_uid, "frame_of_reference_uid": ident["FrameOfReferenceUID"],
            "series_number": int(series_number), "window": {"centre": centres, "width": widths, "names": names}}
