"""What a folder of DICOM files holds, read from their headers with pydicom: which series (a
folder of two is refused, naming both, rather than stacked as one), gaps in a series' slice
positions (ITK re-spaces such a series evenly), and a single slice's thickness (ITK gives it
1 mm whatever the file says)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["series_in", "several_series_message", "slice_gap", "slice_thickness"]


def _headers(files):
    """(path, dataset without pixels) of each file pydicom reads; [] without pydicom."""
    try:
        import pydicom
    except ImportError:
        return []
    out = []
    for f in files:
        try:
            out.append((Path(f), pydicom.dcmread(f, stop_before_pixels=True)))
        except Exception:  # noqa: BLE001 - not a DICOM file: left to the reader that follows
            continue
    return out


def series_in(folder) -> list:
    """[{"uid", "description", "number", "files"}] of the DICOM series among the files of
    ``folder``, most files first; [] without pydicom."""
    files = sorted(p for p in Path(folder).iterdir() if p.is_file())
    found: dict = {}
    for path, ds in _headers(files):
        uid = str(getattr(ds, "SeriesInstanceUID", "") or "")
        s = found.setdefault(uid, {"uid": uid, "description": str(getattr(ds, "SeriesDescription", "") or ""),
                                   "number": getattr(ds, "SeriesNumber", None), "files": []})
        s["files"].append(path)
    return sorted(found.values(), key=lambda s: -len(s["files"]))


def several_series_message(folder, series) -> str:
    """One line naming each series of ``folder`` and how to choose one."""
    parts = [f"'{s['description'] or 'no description'}' (series {s['number'] if s['number'] is not None else '?'}, "
             f"{len(s['files'])} files, SeriesInstanceUID {s['uid'] or '?'})" for s in series]
    return (f"{folder}: holds {len(series)} DICOM series, not one acquisition: {'; '.join(parts)}; move each "
            "series into its own subfolder and give that folder (or name one file of the series you mean)")


def slice_gap(files) -> str | None:
    """A sentence naming where the slice positions of ``files`` (one series) jump by more than 1.5
    times their usual step, or None when evenly spaced (or not known)."""
    normal, positions = None, []
    for _, ds in _headers(files):
        ipp, iop = getattr(ds, "ImagePositionPatient", None), getattr(ds, "ImageOrientationPatient", None)
        if ipp is None or iop is None or len(ipp) != 3 or len(iop) != 6:
            return None
        if normal is None:
            normal = np.cross(np.asarray(iop[:3], float), np.asarray(iop[3:], float))
        positions.append(float(np.dot(normal, np.asarray(ipp, float))))
    if len(positions) < 3:
        return None
    z = np.sort(np.asarray(positions))
    steps = np.diff(z)
    step = float(np.median(steps))
    if step <= 0:
        return None
    big = np.nonzero(steps > 1.5 * step)[0]
    if not big.size:
        return None
    gaps = ", ".join(f"{z[i]:g} to {z[i + 1]:g} mm (about {round(steps[i] / step) - 1} slices missing)"
                     for i in big[:3])
    return (f"the slice positions jump where slices are missing: {gaps}, against a step of {step:g} mm; "
            "the series is read as evenly spaced, so every slice beyond a gap lies out of place: "
            "find the missing files, or resample the series onto an even grid first")


def slice_thickness(path) -> float | None:
    """SliceThickness (mm) of the DICOM file ``path``, or None when absent or not positive."""
    got = _headers([path])
    if not got:
        return None
    try:
        value = float(getattr(got[0][1], "SliceThickness", None))
    except (TypeError, ValueError):
        return None
    return value if value > 0 and np.isfinite(value) else None
