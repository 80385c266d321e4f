"""NeXus NXtomo files: projections, flat and dark fields in one detector stack, told apart by
``image_key``.

The NXtomo application definition keeps every frame in the NXdetector group's ``data`` (frames,
rows, columns) with ``image_key`` per frame: 0 projection, 1 flat field, 2 dark field, 3 invalid
(skipped). The angle of each frame is the NXsample group's ``rotation_angle``, in the unit its
``units`` attribute names (degrees when it says nothing, as NXtomo prescribes). Groups are found by
their ``NX_class`` attribute, so ``/entry/instrument/detector/data`` and
``/entry/sample/rotation_angle`` are found under whatever names the writer chose; ``image_key``
may sit in the detector group or beside the data in the entry's NXdata group.
"""
from __future__ import annotations

import numpy as np

__all__ = ["is_nxtomo", "read_nxtomo", "angle_values"]


def _cls(obj) -> str:
    v = obj.attrs.get("NX_class", b"")
    return v.decode() if isinstance(v, bytes) else str(v)


def _groups(group, nx_class):
    """Every group below ``group`` (itself included) of that NX_class, depth first."""
    import h5py

    found = [group] if _cls(group) == nx_class else []
    for item in group.values():
        if isinstance(item, h5py.Group):
            found.extend(_groups(item, nx_class))
    return found


def _entries(f):
    import h5py

    entries = [g for g in f.values() if isinstance(g, h5py.Group) and _cls(g) == "NXentry"]
    tomo = [e for e in entries if _text(e.get("definition")) == "NXtomo"]
    return tomo or entries


def _text(ds) -> str:
    if ds is None:
        return ""
    v = ds[()]
    if isinstance(v, np.ndarray):
        v = v.reshape(-1)[0] if v.size else b""
    return v.decode() if isinstance(v, bytes) else str(v)


def is_nxtomo(f) -> bool:
    """True when the open HDF5 file ``f`` has an NXentry with an NXdetector holding ``data``."""
    return any("data" in d for e in _entries(f) for d in _groups(e, "NXdetector"))


def _find(entry, groups, name):
    for g in groups:
        if name in g:
            return g[name]
    for g in _groups(entry, "NXdata"):
        if name in g:
            return g[name]
    return None


def angle_values(ds, what) -> np.ndarray:
    """The angles dataset ``ds`` as float64 (flat); ValueError naming it when it holds text (some
    writers store each angle as a string) or anything else that is not real numbers."""
    values = np.asarray(ds[()])
    if values.dtype.kind in "SUOa":
        sample = values.reshape(-1)[:1].tolist()
        raise ValueError(f"{what}: the angles dataset holds text ({values.dtype}, e.g. {sample!r}), not numbers; "
                         "write the angles as a numeric (float) dataset, or give them with --angles")
    if values.dtype.kind not in "biuf":
        raise ValueError(f"{what}: the angles dataset holds {values.dtype}, not real numbers; write the angles as "
                         "a numeric (float) dataset, or give them with --angles")
    return values.astype(np.float64).reshape(-1)


def _degrees(ds, what) -> np.ndarray:
    units = ds.attrs.get("units", b"degree")
    units = (units.decode() if isinstance(units, bytes) else str(units)).strip().lower()
    values = angle_values(ds, what)
    if units in ("degree", "degrees", "deg", "°"):
        return values
    if units in ("rad", "radian", "radians"):
        return np.rad2deg(values)
    raise ValueError(f"{what}: unknown angle units {units!r} (expected degrees or radians)")


def read_nxtomo(f, path) -> dict:
    """{"data", "flats", "darks", "angles_deg", "notes"} from the open HDF5 file ``f`` (module doc);
    ValueError naming what is missing."""
    for entry in _entries(f):
        detectors = [d for d in _groups(entry, "NXdetector") if "data" in d]
        if not detectors:
            continue
        det = detectors[0]
        data = det["data"]
        if data.ndim != 3:
            raise ValueError(f"{path}:{data.name}: expected frames (n, rows, columns), got shape {data.shape}")
        key_ds = _find(entry, [det], "image_key")
        notes = []
        if key_ds is None:
            keys = np.zeros(data.shape[0], int)
            notes.append("no image_key: every frame taken as a projection")
        else:
            keys = np.asarray(key_ds[()]).astype(int).reshape(-1)
            if keys.size != data.shape[0]:
                raise ValueError(f"{path}:{key_ds.name}: {keys.size} image keys for {data.shape[0]} frames")
            unknown = sorted(set(keys.tolist()) - {0, 1, 2, 3})
            if unknown:
                raise ValueError(f"{path}:{key_ds.name}: image keys {unknown} are not NXtomo's 0 (projection), "
                                 "1 (flat), 2 (dark) or 3 (invalid)")
        if not np.any(keys == 0):
            raise ValueError(f"{path}: image_key marks no frame as a projection (0)")
        angle_ds = _find(entry, _groups(entry, "NXsample"), "rotation_angle")
        angles = None
        if angle_ds is not None:
            all_angles = _degrees(angle_ds, f"{path}:{angle_ds.name}")
            if all_angles.size != data.shape[0]:
                raise ValueError(f"{path}:{angle_ds.name}: {all_angles.size} angles for {data.shape[0]} frames")
            angles = all_angles[keys == 0]
        else:
            notes.append("no rotation_angle")
        stack = np.asarray(data[()], np.float32)
        pick = {k: stack[keys == k] for k in (0, 1, 2)}
        return {"data": pick[0], "flats": pick[1] if len(pick[1]) else None,
                "darks": pick[2] if len(pick[2]) else None, "angles_deg": angles,
                "notes": notes + ([f"{int(np.sum(keys == 3))} invalid frames (image_key 3) skipped"]
                                  if np.any(keys == 3) else []),
                "layout": f"NXtomo ({data.name})"}
    raise ValueError(f"{path}: no NXentry with an NXdetector holding 'data'")
