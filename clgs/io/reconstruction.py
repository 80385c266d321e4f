"""Writing a reconstruction's volume: one file, or ``volume.nii.gz`` and ``volume.npy`` in a run
folder, in the input's array order (the geometry's ``orientation``) and in the units asked for.

Methods compute attenuation in 1/mm. ``hu=True`` writes Hounsfield units instead, at the X-ray
energy ``kev`` (given, or the one the scan records: a simulation of a CT in HU converted them at
it); without a known energy it is an error, since the conversion needs water's attenuation at
that energy. The units go into the files' headers (:func:`clgs.io.volume.save_volume`); the
record returned here is what a run's ``report.json`` says of them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from clgs.io import units as _units
from clgs.io.volume import save_volume

__all__ = ["output_units", "save_reconstruction"]


def output_units(hu: bool = False, kev=None, meta=None) -> dict:
    """The units record of a reconstruction written in 1/mm, or in HU (``hu``) at ``kev`` or at the
    energy ``meta`` (a scan's) records. Raises :class:`clgs.io.units.UnitsError` when HU are
    asked for and no energy is known, or the energy is outside 40-150 keV."""
    if not hu:
        if kev is not None:
            raise _units.UnitsError("an X-ray energy (kev) only matters for Hounsfield units: add hu (--to-hu)")
        return _units.units_record(_units.MU)
    if kev is None:
        kev = _units.recorded_kev(meta or {})
    if kev is None:
        raise _units.UnitsError(
            "Hounsfield units need the X-ray energy, and this scan records none (only a scan simulated from a "
            "CT in Hounsfield units, `clgs simulate --hu --kev E`, does): give it with --kev (40-150 keV), "
            "or leave out --to-hu for attenuation in 1/mm")
    _units.water_mu(kev)  # the table's range, with its own message
    return _units.units_record(_units.HU, kev)


def save_reconstruction(out, volume, geometry, *, hu: bool = False, kev=None, meta=None,
                        folder: bool | None = None, overwrite: bool = True) -> dict:
    """Write ``volume`` (Z, Y, X, attenuation in 1/mm) to ``out``: a volume file (``.nii.gz``,
    ``.nii``, ``.npy``, ``.mha``, ``.nrrd``) or, when ``folder`` (default: ``out`` has no volume
    suffix), ``out/volume.nii.gz`` and ``out/volume.npy``. ``hu``, ``kev`` and ``meta`` as for
    :func:`output_units`. Returns the units record (``{"units": "1/mm"}`` or HU with ``kev``)."""
    from clgs.io.suffixes import VOLUME_SUFFIXES

    rec = output_units(hu, kev, meta)
    vol = np.asarray(volume, np.float32)
    if rec["units"] == _units.HU:
        vol = _units.mu_to_hu(vol, rec["kev"])
    out = Path(out)
    if folder is None:
        folder = not out.name.lower().endswith(tuple(VOLUME_SUFFIXES))
    kw = dict(units=rec["units"], kev=rec.get("kev"), overwrite=overwrite)
    if not folder:
        save_volume(out, vol, geometry, **kw)
        return rec
    out.mkdir(parents=True, exist_ok=True)
    save_volume(out / "volume.nii.gz", vol, geometry, **kw)
    save_volume(out / "volume.npy", vol, geometry, **kw)
    return rec
