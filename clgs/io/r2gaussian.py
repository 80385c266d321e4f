"""R2-Gaussian dataset folders, read as they are and written back.

Layout (as produced by R2-Gaussian's data generators)::

    meta_data.json   {"scanner": {...}, "vol": "vol_gt.npy", "bbox": [[x0,y0,z0],[x1,y1,z1]],
                      "proj_train": [{"file_path": "proj_train/proj_train_0000.npy", "angle": rad}, ...],
                      "proj_test":  [...]}
    vol_gt.npy       the ground-truth volume (their real-data generator names the key "ct")
    proj_train/*.npy one (V, U) projection per view; likewise proj_test/

Axis and unit facts, learnt from R2-Gaussian's ``data_generator/synthetic_dataset/generate_data.py``
(projections made by ``tigre.Ax(np.transpose(vol, (2, 1, 0)), ...)[:, ::-1, :]``),
``r2_gaussian/utils/ct_utils.py`` (``get_geometry``: reverses ``nVoxel``, ``sVoxel`` and
``offOrigin``, maps ``offDetector`` [u, v] to TIGRE's [v, u]; FDK is run on ``projs[:, ::-1, :]``
and its (Z, Y, X) output transposed back with ``(2, 1, 0)``), the scanner files in
``data_generator/synthetic_dataset/scanner/*.yml`` and ``r2_gaussian/dataset/dataset_readers.py``
(``angle2pose``: camera at ``DSO (cos a, sin a, 0)``, image x axis ``(-sin a, cos a, 0)``, image
y axis ``(0, 0, -1)``, so image rows run *down* the rotation axis):

* Volume: stored [x, y, z]; ours is (Z, Y, X) = ``vol.transpose(2, 1, 0)`` (a pure transpose,
  no flip: index i grows with x, j with y, k with z in both).
* Projections: each file is (V, U) with row 0 at the *top* (largest z), like an image; TIGRE and
  clgs put row 0 at the bottom (detector v grows with z), so ours = ``theirs[::-1, :]`` (and the
  same flip on writing). Columns are not flipped: both run along ``(-sin a, cos a, 0)``.
* Angles: per view, radians, the same angle as ours (source at ``DSO (cos a, sin a, 0)``).
  ``startAngle``/``totalAngle`` in the scanner dict are degrees and only informative.
* Scanner dict: ``nDetector``, ``sDetector``/``dDetector`` are [V, U] (as ours); ``nVoxel``,
  ``sVoxel``/``dVoxel`` and ``offOrigin`` are [x, y, z] (ours are (Z, Y, X): reversed);
  ``offDetector`` is [u, v] (ours (V, U): reversed). ``dVoxel``/``dDetector`` may be absent and
  then follow from the sizes ``s*`` / counts ``n*``.
* Units: lengths are whatever unit the dataset used (their synthetic sets put the volume in a
  2-unit cube; real sets in mm scaled by an object factor) and are read as mm; projections are
  line integrals in that same unit, read unchanged. R2-Gaussian itself rescales both into its
  [-1, 1]^3 scene when loading; clgs does that in :class:`~clgs.geometry.Geometry`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from clgs.geometry import Geometry, GeometryError
from clgs.io import atomic
from clgs.io.validate import NEG_TOLERANCE, ScanError, check_projections, inside_folder, read_json, read_npy

__all__ = ["is_r2gaussian_folder", "to_r2gaussian_folder", "geometry_from_scanner",
           "scanner_from_geometry", "META_DATA"]

META_DATA = "meta_data.json"


def is_r2gaussian_folder(folder) -> bool:
    return (Path(folder) / META_DATA).is_file()


def _vec(scanner, key, n):
    try:
        arr = np.asarray(scanner[key], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ScanError(f"scanner {key!r} is not a list of numbers: {scanner[key]!r}") from exc
    if arr.size != n:
        raise ScanError(f"scanner {key!r} must have {n} entries, got {scanner[key]!r}")
    return arr


def geometry_from_scanner(scanner: dict, angles) -> Geometry:
    """A :class:`Geometry` from an R2-Gaussian (TIGRE-layout) scanner dict and per-view angles (rad)."""
    missing = [k for k in ("DSD", "DSO", "nDetector", "nVoxel") if k not in scanner]
    if "dDetector" not in scanner and "sDetector" not in scanner:
        missing.append("dDetector or sDetector")
    if "dVoxel" not in scanner and "sVoxel" not in scanner:
        missing.append("dVoxel or sVoxel")
    if missing:
        raise ScanError(f"scanner description is missing {', '.join(missing)}")
    n_det = _vec(scanner, "nDetector", 2)  # [V, U]
    d_det = _vec(scanner, "dDetector", 2) if "dDetector" in scanner else _vec(scanner, "sDetector", 2) / n_det
    n_vox_xyz = _vec(scanner, "nVoxel", 3)
    d_vox_xyz = _vec(scanner, "dVoxel", 3) if "dVoxel" in scanner else _vec(scanner, "sVoxel", 3) / n_vox_xyz
    off_origin_xyz = _vec(scanner, "offOrigin", 3) if "offOrigin" in scanner else np.zeros(3)
    off_det_uv = _vec(scanner, "offDetector", 2) if "offDetector" in scanner else np.zeros(2)
    try:
        return Geometry(
            DSD=scanner["DSD"], DSO=scanner["DSO"],
            nDetector=tuple(n_det), dDetector=tuple(d_det),
            nVoxel=tuple(n_vox_xyz[::-1]), dVoxel=tuple(d_vox_xyz[::-1]),
            offOrigin=tuple(off_origin_xyz[::-1]), offDetector=tuple(off_det_uv[::-1]),
            angles=np.asarray(angles, dtype=np.float64), mode=str(scanner.get("mode", "cone")),
        )
    except GeometryError as exc:
        raise ScanError(f"invalid scanner description: {exc}") from exc


def _angle_span(angles: np.ndarray):
    """(startAngle, totalAngle) in degrees, as R2-Gaussian's generator defines them."""
    a = np.asarray(angles, float)
    if a.size < 2:
        return float(np.degrees(a[0])), 0.0
    steps = np.diff(a)
    total = (a[-1] - a[0]) * a.size / (a.size - 1) if np.allclose(steps, steps[0]) else a[-1] - a[0]
    return float(np.degrees(a[0])), float(np.degrees(total))


def scanner_from_geometry(geometry: Geometry, acquisition: dict | None = None) -> dict:
    """The R2-Gaussian scanner dict for a :class:`Geometry` (TIGRE layout, see the module doc)."""
    g = geometry
    if not g.is_circular:
        raise ScanError("R2-Gaussian's dataset format holds circular scans only (DSO, DSD, angles); this scan's "
                        "geometry is given per view as vectors")
    start, total = _angle_span(g.angles)
    acq = acquisition or {}
    noise = bool(acq.get("noise", False))
    d = {
        "mode": g.mode,
        "filter": None,
        "DSD": g.DSD,
        "DSO": g.DSO,
        "nDetector": [int(v) for v in g.nDetector],
        "sDetector": [float(v) for v in g.sDetector],
        "dDetector": [float(v) for v in g.dDetector],
        "nVoxel": [int(v) for v in g.nVoxel[::-1]],
        "sVoxel": [float(v) for v in g.sVoxel[::-1]],
        "dVoxel": [float(v) for v in g.dVoxel[::-1]],
        "offOrigin": [float(v) for v in g.offOrigin[::-1]],
        "offDetector": [float(v) for v in g.offDetector[::-1]],
        "accuracy": 0.5,
        "totalAngle": total,
        "startAngle": start,
        "noise": noise,
    }
    if noise:
        d["possion_noise"] = acq.get("I0")
        d["gaussian_noise"] = [0.0, acq.get("sigma")]
    return d


def _read_meta(folder: Path) -> dict:
    path = folder / META_DATA
    meta = read_json(path)
    if not isinstance(meta, dict) or not isinstance(meta.get("scanner"), dict):
        raise ScanError(f"{path}: not an R2-Gaussian description (no 'scanner' section)")
    return meta


def read_parts(folder, split: str = "train", neg_tolerance: float = NEG_TOLERANCE) -> tuple:
    """Read an R2-Gaussian dataset folder: (geometry, projections, truth, meta) of a
    :class:`clgs.io.scan.Scan` (``Scan.load`` and :func:`clgs.io.scan.read_r2gaussian` make it)
    of the views of ``split`` (train or test).

    The truth (``vol`` or ``ct`` key) is transposed to (Z, Y, X); each projection is flipped
    vertically (see the module doc).
    """
    folder = Path(folder)
    if split not in ("train", "test"):
        raise ScanError(f"split must be 'train' or 'test', got {split!r}")
    meta = _read_meta(folder)
    scanner = meta["scanner"]
    entries = meta.get(f"proj_{split}")
    if not isinstance(entries, list):
        raise ScanError(f"{folder / META_DATA}: no 'proj_{split}' list of views")
    if not entries:
        raise ScanError(f"{folder / META_DATA}: 'proj_{split}' lists zero views; a scan needs at least one")
    try:
        angles = np.array([float(e["angle"]) for e in entries])
        files = [str(e["file_path"]) for e in entries]
    except (KeyError, TypeError, ValueError) as exc:
        raise ScanError(f"{folder / META_DATA}: each view needs 'file_path' and 'angle' (radians): {exc}") from exc
    geometry = geometry_from_scanner(scanner, angles)
    views = []
    for f in files:
        p = read_npy(inside_folder(folder, f, "projection", META_DATA), "projection", META_DATA)
        if p.ndim != 2 or tuple(p.shape) != tuple(geometry.nDetector):
            raise ScanError(f"{folder / f}: projection of shape {p.shape} does not match the scanner's "
                            f"nDetector [V, U] = {list(geometry.nDetector)}")
        views.append(p[::-1, :])  # image rows (top = +z) -> detector rows (v grows with z)
    proj = check_projections(np.stack(views), geometry, neg_tolerance, source=str(folder))
    truth = None
    vol_key = "vol" if "vol" in meta else ("ct" if "ct" in meta else None)
    if vol_key is not None and meta[vol_key]:
        vol = read_npy(inside_folder(folder, str(meta[vol_key]), "volume", META_DATA), "volume", META_DATA)
        expected = tuple(geometry.nVoxel[::-1])
        if vol.ndim != 3 or tuple(vol.shape) != expected:
            raise ScanError(f"{folder / str(meta[vol_key])}: volume of shape {vol.shape} does not match the "
                            f"scanner's nVoxel [x, y, z] = {list(expected)}")
        truth = np.ascontiguousarray(vol.transpose(2, 1, 0)).astype(np.float32)  # [x,y,z] -> (Z,Y,X)
    acquisition = {"noise": bool(scanner.get("noise", False))}
    if acquisition["noise"]:
        gauss = scanner.get("gaussian_noise")
        acquisition.update(I0=scanner.get("possion_noise"),
                           sigma=(gauss[1] if isinstance(gauss, (list, tuple)) and len(gauss) > 1 else gauss))
    scan_meta = {
        "acquisition": acquisition,
        "provenance": {"source": "r2gaussian", "folder": str(folder), "split": split, "scanner": scanner},
    }
    return geometry, proj, truth, scan_meta


def to_r2gaussian_folder(scan, folder, test=None, overwrite: bool = False) -> Path:
    """Write ``scan`` (a :class:`clgs.io.scan.Scan`) as an R2-Gaussian dataset folder (atomically):
    its views become ``proj_train``, those of ``test`` (same scanner, other angles) ``proj_test``.
    The truth, if any, goes to ``vol_gt.npy`` in [x, y, z] order; every projection is flipped to
    image rows."""
    folder = Path(folder)
    if test is not None:
        gt, gs = test.geometry.to_dict(), scan.geometry.to_dict()
        gt.pop("angles"), gs.pop("angles")
        if gt != gs:
            raise ScanError("the test views must come from the same scanner geometry as the training views")
    scanner = scanner_from_geometry(scan.geometry, scan.meta.get("acquisition"))
    g = scan.geometry
    lo = np.asarray(g.offOrigin[::-1]) - g.sVoxel[::-1] / 2
    hi = np.asarray(g.offOrigin[::-1]) + g.sVoxel[::-1] / 2
    meta = {"scanner": scanner, "bbox": [lo.tolist(), hi.tolist()]}
    if scan.truth is not None:
        meta["vol"] = "vol_gt.npy"
    with atomic.atomic_dir(folder, overwrite=overwrite) as tmp:
        for split, part in (("proj_train", scan), ("proj_test", test)):
            meta[split] = []
            (tmp / split).mkdir()
            if part is None:
                continue
            for i, (proj, angle) in enumerate(zip(part.projections, part.geometry.angles)):
                name = f"{split}/{split}_{i:04d}.npy"
                atomic.save_npy(tmp / name, np.ascontiguousarray(proj[::-1, :], dtype=np.float32))
                meta[split].append({"file_path": name, "angle": float(angle)})
        if scan.truth is not None:
            atomic.save_npy(tmp / "vol_gt.npy", np.ascontiguousarray(scan.truth.transpose(2, 1, 0), dtype=np.float32))
        atomic.write_json(tmp / META_DATA, meta, indent=4)
    return folder
