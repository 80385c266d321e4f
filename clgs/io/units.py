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
