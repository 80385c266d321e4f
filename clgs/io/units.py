"""Hounsfield units and linear attenuation (1/mm), at a stated X-ray energy.

``HU = 1000 (mu - mu_water) / mu_water``, so ``mu = mu_water (1 + HU / 1000)``: air (-1000 HU)
is 0, water 0 HU is ``mu_water``. ``mu_water`` depends on the energy; the table holds water's
total attenuation coefficient with coherent scattering (NIST XCOM, density 1 g/cm^3) at a few
energies, interpolated log-log in between. Attenuation below 0 (HU below -1000, noise in air)
is clipped to 0 when converting to attenuation, which is what the projector needs.
"""
from __future__ import annotations

import numpy as np

from clgs.errors import ClgsError

#: keV -> water's linear attenuation in 1/mm (NIST XCOM, total with coherent scattering)
WATER_MU_PER_MM = {40: 0.02683, 50: 0.02269, 60: 0.02059, 80: 0.01837, 100: 0.01707, 150: 0.01505}
DEFAULT_KEV = 70.0


class UnitsError(ClgsError, ValueError):
    """An energy outside the table, or values that cannot be Hounsfield units."""


def water_mu(kev: float = DEFAULT_KEV) -> float:
    """Water's linear attenuation (1/mm) at ``kev`` (40-150 keV)."""
    kev = float(kev)
    keys = sorted(WATER_MU_PER_MM)
    if not (keys[0] <= kev <= keys[-1]):
        raise UnitsError(f"energy {kev:g} keV is outside the water table ({keys[0]}-{keys[-1]} keV)")
    logs = np.log([WATER_MU_PER_MM[k] for k in keys])
    return float(np.exp(np.interp(np.log(kev), np.log(keys), logs)))


def hu_to_mu(hu, kev: float = DEFAULT_KEV) -> np.ndarray:
    """Hounsfield units -> attenuation in 1/mm (float32, clipped at 0)."""
    h = np.asarray(hu, dtype=np.float64)
    if not np.all(np.isfinite(h)):
        raise UnitsError("the volume contains NaN or Inf; Hounsfield units are finite numbers")
    return np.clip(water_mu(kev) * (1.0 + h / 1000.0), 0.0, None).astype(np.float32)


def mu_to_hu(mu, kev: float = DEFAULT_KEV) -> np.ndarray:
    """Attenuation in 1/mm -> Hounsfield units (float32)."""
    w = water_mu(kev)
    return (1000.0 * (np.asarray(mu, dtype=np.float64) - w) / w).astype(np.float32)


def unit_label(hu: bool, kev: float = DEFAULT_KEV) -> str:
    """How a volume file names its values: ``HU at 70 keV`` or ``attenuation 1/mm``."""
    return f"HU at {float(kev):g} keV" if hu else "attenuation 1/mm"


def record_unit(path, label: str):
    """Write ``label`` (e.g. :func:`unit_label`) into the header of a volume file clgs wrote: a
    NIfTI's ``descrip`` field, a MetaImage's or NRRD's ``ValueUnit`` field. The file is rewritten
    atomically. Returns False for ``.npy`` (no header: nothing recorded), True otherwise."""
    from pathlib import Path

    from clgs.io import atomic

    path = Path(path)
    name = path.name.lower()
    if name.endswith(".npy"):
        return False
    if name.endswith((".nii", ".nii.gz")):
        import nibabel as nib

        img = nib.load(str(path))
        data = np.asanyarray(img.dataobj)
        hdr = img.header.copy()
        hdr["descrip"] = label.encode()[:80]
        new = nib.Nifti1Image(data, img.affine, hdr)
        with atomic.atomic_path(path, True) as tmp:
            nib.save(new, str(tmp))
        return True
    import os
    import shutil
    import tempfile

    import SimpleITK as sitk

    img = sitk.ReadImage(str(path))
    img.SetMetaData("ValueUnit", label)
    # made under its own name in a folder beside it (a detached header names its data file), then
    # moved in: data files first, the header last
    tmpdir = Path(tempfile.mkdtemp(prefix=".clgs-tmp-", dir=path.parent))
    try:
        sitk.WriteImage(img, str(tmpdir / path.name), True)
        for f in sorted(tmpdir.iterdir(), key=lambda f: f.name == path.name):
            os.replace(f, path.parent / f.name)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return True


def recorded_unit(path) -> str | None:
    """The value unit a volume file's header records (:func:`record_unit`), or None."""
    from pathlib import Path

    path = Path(path)
    name = path.name.lower()
    if name.endswith(".npy"):
        return None
    if name.endswith((".nii", ".nii.gz")):
        import nibabel as nib

        text = bytes(nib.load(str(path)).header["descrip"]).split(b"\0")[0].decode("latin-1").strip()
        return text or None
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.ReadImageInformation()
    return reader.GetMetaData("ValueUnit") if reader.HasMetaDataKey("ValueUnit") else None
