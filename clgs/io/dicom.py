"""Volumes out as a DICOM CT series: one file per slice, in Hounsfield units, where the volume lies.

DICOM CT viewers and PACS expect Hounsfield units in 16-bit integers, so attenuation (1/mm) is
converted at a stated X-ray energy (:mod:`clgs.io.units`) and rounded to the nearest HU (an
error of at most 0.5 HU; values beyond the int16 range are clipped and counted). Positions follow
DICOM's patient frame (LPS): the slices' ``ImagePositionPatient`` and ``ImageOrientationPatient``
place every voxel at the same world point as clgs's NIfTI files do (whose frame is RAS). UIDs are
derived from the data and its grid, so the same volume gives the same files. Reading a series back
is :func:`clgs.io.volume.load_volume` (SimpleITK's GDCM reader).
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from clgs.io import atomic
from clgs.io.units import DEFAULT_KEV, mu_to_hu

__all__ = ["save_dicom_series"]

#: CT Image Storage
_CT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.2"


def _uid(*parts) -> str:
    """A UID under the UUID-derived root 2.25 (no registered root needed), from a digest."""
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else str(p).encode())
    return "2.25." + str(int.from_bytes(h.digest()[:16], "big"))


def save_dicom_series(folder, volume, spacing_zyx, origin_xyz, *, kev: float = DEFAULT_KEV,
                      description: str = "clgs volume", overwrite: bool = False) -> dict:
    """Write ``volume`` (Z, Y, X attenuation in 1/mm; voxel [0, 0, 0] centred at ``origin_xyz``,
    RAS mm) as a DICOM CT series in ``folder`` (made atomically). Returns a report: files, HU
    range, clipped voxel count."""
    from clgs.io.volume import LPS, require_simpleitk

    sitk = require_simpleitk()
    vol = np.asarray(volume, np.float64)
    if vol.ndim != 3:
        raise ValueError(f"a DICOM series needs a 3-D volume, got shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise ValueError("the volume holds NaN or Inf: DICOM stores integers; clean the volume first")
    sp = np.asarray(spacing_zyx, float)
    org = np.asarray(origin_xyz, float)
    hu = np.rint(mu_to_hu(vol, kev))
    clipped = int(np.count_nonzero((hu < -32768) | (hu > 32767)))
    hu16 = np.clip(hu, -32768, 32767).astype(np.int16)
    digest = hashlib.sha256(hu16.tobytes()).hexdigest()
    study = _uid("study", digest, sp.tobytes(), org.tobytes())
    series = _uid("series", digest, sp.tobytes(), org.tobytes(), kev)
    # rows run along +x (RAS) = -x (LPS), columns along +y (RAS) = -y (LPS)
    orientation = "\\".join(f"{v:g}" for v in (*(np.array([1.0, 0, 0]) * LPS), *(np.array([0, 1.0, 0]) * LPS)))
    folder = Path(folder)
    with atomic.atomic_dir(folder, overwrite=overwrite) as tmp:
        writer = sitk.ImageFileWriter()
        writer.KeepOriginalImageUIDOn()
        for k in range(hu16.shape[0]):
            img = sitk.GetImageFromArray(hu16[k])
            img.SetSpacing((float(sp[2]), float(sp[1])))
            pos = (org + np.array([0.0, 0.0, k * sp[0]])) * LPS
            tags = {
                "0008|0016": _CT_SOP_CLASS, "0008|0018": _uid(series, k), "0008|0060": "CT",
                "0008|103e": description[:64], "0010|0010": "clgs", "0010|0020": "clgs",
                "0020|000d": study, "0020|000e": series, "0020|0011": "1", "0020|0013": str(k + 1),
                "0020|0032": "\\".join(f"{v:.6f}" for v in pos), "0020|0037": orientation,
                "0020|1041": f"{pos[2]:.6f}", "0018|0050": f"{sp[0]:.6f}",
                "0028|0030": f"{sp[1]:.6f}\\{sp[2]:.6f}",
                "0028|1052": "0", "0028|1053": "1", "0028|1054": "HU",
                "0018|0060": "", "0008|0008": "DERIVED\\SECONDARY\\AXIAL",
                "0020|4000": f"attenuation converted at {kev:g} keV",
            }
            for key, value in tags.items():
                img.SetMetaData(key, value)
            writer.SetFileName(str(Path(tmp) / f"slice{k + 1:04d}.dcm"))
            writer.Execute(img)
    return {"folder": str(folder), "files": int(hu16.shape[0]), "kev": float(kev),
            "hu_min": int(hu16.min()), "hu_max": int(hu16.max()), "clipped": clipped}
