"""Hounsfield units and linear attenuation (1/mm), at a stated X-ray energy.

``HU = 1000 (mu - mu_water) / mu_water``, so ``mu = mu_water (1 + HU / 1000)``: air (-1000 HU)
is 0, water 0 HU is ``mu_water``. ``mu_water`` depends on the energy; the table holds water's
total attenuation coefficient with coherent scattering (NIST XCOM, density 1 g/cm^3) at a few
energies, interpolated log-log in between. Attenuation below 0 (HU below -1000, noise in air)
is clipped to 0 when converting to attenuation, which is what the projector needs.

Every attenuation volume clgs writes says its unit (:func:`units_record`, :func:`header_text`):
``"1/mm"`` (linear attenuation) or ``"HU"`` (with the energy it was converted at).
:func:`attenuation_doubt` names values no tissue has, for inputs taken as 1/mm.
"""
from __future__ import annotations

import numpy as np

from clgs.errors import ClgsError

#: keV -> water's linear attenuation in 1/mm (NIST XCOM, total with coherent scattering)
WATER_MU_PER_MM = {40: 0.02683, 50: 0.02269, 60: 0.02059, 80: 0.01837, 100: 0.01707, 150: 0.01505}
DEFAULT_KEV = 70.0
MU = "1/mm"  #: linear attenuation per mm, what clgs computes in
HU = "HU"  #: Hounsfield units, at a stated energy
#: above this 99.9th percentile (1/mm) a volume taken as attenuation is not attenuation: water is
#: 0.019/mm at 70 keV, cortical bone 0.05-0.06/mm, metal implants below about 2/mm; a volume
#: normalised to [0, 1] sits near 1. Below MU_LOW a value is no attenuation either.
MU_HIGH = 0.3
MU_LOW = -0.01


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


def units_record(units: str = MU, kev: float | None = None) -> dict:
    """What a report says of a volume's values: ``{"units": "1/mm"}``, or for Hounsfield units
    ``{"units": "HU", "kev": ..., "water_mu_per_mm": ...}``."""
    if units == MU:
        return {"units": MU}
    if units != HU:
        raise UnitsError(f"unknown units {units!r}: clgs writes {MU!r} or {HU!r}")
    if kev is None:
        raise UnitsError("Hounsfield units need the X-ray energy (keV) they were converted at")
    return {"units": HU, "kev": float(kev), "water_mu_per_mm": round(water_mu(kev), 6)}


def header_text(units: str = MU, kev: float | None = None) -> tuple:
    """(description, short name) for a volume file's header: NIfTI's ``descrip`` (80 bytes) and
    ``intent_name`` (16 bytes)."""
    rec = units_record(units, kev)
    if rec["units"] == MU:
        return "clgs: linear attenuation mu in 1/mm", "mu 1/mm"
    return (f"clgs: Hounsfield units at {rec['kev']:g} keV (water mu {rec['water_mu_per_mm']:.5f}/mm)",
            f"HU {rec['kev']:g} keV"[:16])


def recorded_kev(meta) -> float | None:
    """The X-ray energy a scan records (``meta.acquisition.kev``: a simulation of a CT in Hounsfield
    units converted them at it), or None."""
    acq = meta.get("acquisition") if isinstance(meta, dict) else None
    kev = acq.get("kev") if isinstance(acq, dict) else None
    return float(kev) if isinstance(kev, (int, float)) and not isinstance(kev, bool) and np.isfinite(kev) else None


def attenuation_doubt(volume, negatives: bool = True) -> str | None:
    """Why ``volume``, taken as attenuation in 1/mm, cannot be one (values no tissue has), or None.

    Looks at the 99.9th percentile (above :data:`MU_HIGH`: normalised to [0, 1], or Hounsfield
    units) and, with ``negatives``, the minimum (below :data:`MU_LOW`). Large volumes are sampled
    (every n-th voxel, about 4 million)."""
    v = np.asarray(volume).reshape(-1)
    if v.size == 0 or not np.issubdtype(v.dtype, np.number):
        return None
    step = max(1, v.size // 4_000_000)
    sample = np.asarray(v[::step], np.float64)
    sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        return None
    high = float(np.percentile(sample, 99.9))
    low = float(sample.min())
    seen = []
    if high > MU_HIGH:
        seen.append(f"its 99.9th percentile is {high:.4g}/mm, more than any tissue attenuates (water is about "
                    "0.019/mm at 70 keV, cortical bone 0.05-0.06/mm, even metal implants stay below about 2/mm)")
    if negatives and low < MU_LOW:
        seen.append(f"its values go down to {low:.4g}, and attenuation is never negative")
    if not seen:
        return None
    return ("read as attenuation in 1/mm, but " + "; ".join(seen) + ". Hounsfield units (a CT): add --hu "
            "(and --kev for the energy); a volume normalised to [0, 1] or in other units: scale it to 1/mm first")


def recorded_units(path) -> dict | None:
    """What a volume file's header says of its values (as :func:`clgs.io.volume.save_volume` writes
    it): ``{"units": "1/mm"}`` or ``{"units": "HU", "kev": ...}``; None when it says nothing (a
    ``.npy``, or a file from elsewhere)."""
    from pathlib import Path

    path = Path(path)
    name = path.name.lower()
    if name.endswith(".npy"):
        return None
    if name.endswith((".nii", ".nii.gz")):
        import nibabel as nib

        short = bytes(nib.load(str(path)).header["intent_name"]).split(b"\0")[0].decode("latin-1").strip()
        if short == "mu 1/mm":
            return {"units": MU}
        if short.startswith("HU ") and short.endswith(" keV"):
            return {"units": HU, "kev": float(short[3:-4])}
        return None
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.ReadImageInformation()
    if not reader.HasMetaDataKey("clgs_units"):
        return None
    out = {"units": reader.GetMetaData("clgs_units")}
    if reader.HasMetaDataKey("clgs_kev"):
        out["kev"] = float(reader.GetMetaData("clgs_kev"))
    return out
