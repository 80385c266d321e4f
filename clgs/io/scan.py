"""The clgs scan folder: projections, scanner geometry and (for simulated scans) the truth.

Layout of a scan folder::

    scan.json            format name and version, Geometry.to_dict(), units, file list, meta
    projections.npy      (n_views, V, U) float32 line integrals
    truth.npy            optional ground truth (Z, Y, X) float32, attenuation in 1/mm
    truth.nii.gz         optional copy of the truth for viewers (affine from the geometry)
    truth_surface.stl    optional true surface, world mm

Projections are line integrals ``-log(I / I0)`` of the attenuation ``mu`` (1/mm) along each ray
(lengths in mm), i.e. the units of ``UNITS``; row ``iv`` of a view grows with z and column ``iu``
with the detector's u axis (see :mod:`clgs.geometry`).

``meta`` holds everything else, as JSON: ``acquisition`` (``noise`` true/false, ``I0``,
``sigma``, ``scatter``, ``seed``), ``provenance`` (what made the scan), optionally ``subject``
and ``anatomy``; further keys are kept as they are.

Negative line integrals: a real or simulated noisy scan has small negatives where the object is
thin (photon counts above the flat field). Values down to ``-neg_tolerance * max(projections)``
(default 5 % of the largest line integral) are set to 0 with a warning, as R2-Gaussian's data
generator does; anything more negative is an error, since it means the file holds something else
(intensities, a flipped sign, a corrupted array).

``Scan.load`` also reads R2-Gaussian dataset folders (``meta_data.json``); see
:mod:`clgs.io.r2gaussian`. A folder is written atomically: a temporary sibling is filled and then
renamed, so a reader never sees a half-written scan.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from clgs.geometry import Geometry, GeometryError
from clgs.io import atomic

__all__ = ["Scan", "ScanError", "ScanWarning", "FORMAT", "VERSION", "UNITS", "NEG_TOLERANCE",
           "check_projections", "is_scan_folder"]

FORMAT = "clgs-scan"
VERSION = 1
UNITS = "line integral of mu (1/mm) x mm"
NEG_TOLERANCE = 0.05
SCAN_JSON = "scan.json"
PROJECTIONS = "projections.npy"
TRUTH = "truth.npy"
TRUTH_NIFTI = "truth.nii.gz"
TRUTH_SURFACE = "truth_surface.stl"


class ScanError(ValueError):
    """A scan that cannot be used: missing files, mismatched shapes, impossible values."""


class ScanWarning(UserWarning):
    """Something was repaired while reading a scan (e.g. tiny negative line integrals set to 0)."""


def check_projections(projections, geometry: Geometry, neg_tolerance: float = NEG_TOLERANCE,
                      source: str = "projections") -> np.ndarray:
    """Validate line integrals against a geometry; return them as float32 (tiny negatives -> 0).

    Errors name what is wrong and what to do: wrong rank, zero views, shape not matching
    (n_views, nDetector), NaN/Inf, line integrals below ``-neg_tolerance * max``.
    """
    p = np.asarray(projections)
    if p.dtype == object or not np.issubdtype(p.dtype, np.number) or np.issubdtype(p.dtype, np.complexfloating):
        raise ScanError(f"{source}: not an array of real numbers (dtype {p.dtype}); line integrals are real")
    if p.ndim != 3:
        raise ScanError(f"{source}: expected (n_views, V, U) line integrals, got an array of shape {p.shape}")
    if p.shape[0] == 0:
        raise ScanError(f"{source}: the scan has zero views; a reconstruction needs at least one projection")
    expected = (geometry.n_views, *geometry.nDetector)
    if tuple(p.shape) != expected:
        raise ScanError(
            f"{source}: shape {tuple(p.shape)} does not match the geometry (n_views, V, U) = {expected}; "
            "check nDetector (V, U order) and the number of angles")
    p = p.astype(np.float32, copy=True)
    bad = ~np.isfinite(p)
    if bad.any():
        views = np.unique(np.nonzero(bad)[0])
        raise ScanError(f"{source}: {int(bad.sum())} values are NaN or Inf (views {views[:10].tolist()}"
                        f"{'...' if views.size > 10 else ''}); the projections are corrupted")
    lo = float(p.min())
    if lo < 0:
        top = float(p.max())
        tol = neg_tolerance * top if top > 0 else 0.0
        if top <= 0:
            raise ScanError(f"{source}: every line integral is <= 0 (down to {lo:.4g}); projections must be "
                            "-log(I/I0) >= 0: were intensities or their logarithm stored with the sign flipped?")
        if lo < -tol:
            raise ScanError(
                f"{source}: line integrals go down to {lo:.4g}, below the tolerance -{tol:.4g} "
                f"({neg_tolerance:.0%} of the largest, {top:.4g}); projections must be -log(I/I0) >= 0: "
                "were intensities stored instead, or the sign flipped?")
        n = int((p < 0).sum())
        warnings.warn(f"{source}: {n} slightly negative line integrals (down to {lo:.3g}, noise) set to 0",
                      ScanWarning, stacklevel=3)
        np.maximum(p, 0.0, out=p)
    return p


def _check_truth(truth, geometry: Geometry, source: str = "truth") -> Optional[np.ndarray]:
    if truth is None:
        return None
    t = np.asarray(truth)
    if t.ndim != 3 or tuple(t.shape) != tuple(geometry.nVoxel):
        raise ScanError(f"{source}: shape {t.shape} does not match the geometry's nVoxel (Z, Y, X) = {geometry.nVoxel}")
    t = t.astype(np.float32, copy=False)
    if not np.all(np.isfinite(t)):
        raise ScanError(f"{source}: the truth volume contains NaN or Inf")
    return t


def is_scan_folder(folder) -> bool:
    return (Path(folder) / SCAN_JSON).is_file()


@dataclass
class Scan:
    """A scan: ``geometry``, ``projections`` (n_views, V, U) float32 line integrals, the ``truth``
    volume (Z, Y, X) or None, ``meta`` (JSON-able dict) and an optional true ``surface``
    ((vertices mm, faces), e.g. :class:`clgs.io.mesh.Mesh`). Checked on construction."""

    geometry: Geometry
    projections: np.ndarray
    truth: Optional[np.ndarray] = None
    meta: dict = field(default_factory=dict)
    surface: Optional[tuple] = None

    def __post_init__(self):
        if not isinstance(self.geometry, Geometry):
            raise ScanError(f"geometry must be a clgs.geometry.Geometry, got {type(self.geometry).__name__}")
        self.projections = check_projections(self.projections, self.geometry)
        self.truth = _check_truth(self.truth, self.geometry)
        self.meta = dict(self.meta or {})
        if self.surface is not None:
            from clgs.io.mesh import Mesh, _check

            v, f = self.surface
            self.surface = Mesh(*_check(v, f))

    @property
    def n_views(self) -> int:
        return int(self.projections.shape[0])

    def subset(self, views: Sequence[int]) -> "Scan":
        """The scan restricted to some views (e.g. every 10th for a sparse-view experiment)."""
        idx = np.asarray(views, dtype=int).reshape(-1)
        if idx.size == 0:
            raise ScanError("a subset needs at least one view")
        if idx.min() < -self.n_views or idx.max() >= self.n_views:
            raise ScanError(f"view indices must lie in [0, {self.n_views}), got {idx.tolist()}")
        meta = dict(self.meta)
        meta["views"] = idx.tolist()
        return Scan(self.geometry.with_angles(self.geometry.angles[idx]), self.projections[idx],
                    self.truth, meta, self.surface)

    # ------------------------------------------------------------------------------ writing
    def to_json(self) -> dict:
        files = {"projections": PROJECTIONS}
        if self.truth is not None:
            files.update(truth=TRUTH, truth_nifti=TRUTH_NIFTI)
        if self.surface is not None:
            files["truth_surface"] = TRUTH_SURFACE
        return {
            "format": FORMAT,
            "version": VERSION,
            "units": UNITS,
            "geometry": self.geometry.to_dict(),
            "projections_shape": list(self.projections.shape),
            "files": files,
            "meta": self.meta,
        }

    def save(self, folder, overwrite: bool = False, truth_nifti: bool = True) -> Path:
        """Write the scan folder atomically (FileExistsError if it exists and not ``overwrite``)."""
        from clgs.io.volume import save_volume

        folder = Path(folder)
        doc = self.to_json()
        if not truth_nifti:
            doc["files"].pop("truth_nifti", None)
        with atomic.atomic_dir(folder, overwrite=overwrite) as tmp:
            atomic.save_npy(tmp / PROJECTIONS, self.projections)
            if self.truth is not None:
                atomic.save_npy(tmp / TRUTH, self.truth)
                if truth_nifti:
                    save_volume(tmp / TRUTH_NIFTI, self.truth, self.geometry)
            if self.surface is not None:
                from clgs.io.mesh import save_mesh

                save_mesh(tmp / TRUTH_SURFACE, self.surface.vertices, self.surface.faces)
            atomic.write_json(tmp / SCAN_JSON, doc)
        return folder

    # ------------------------------------------------------------------------------ reading
    @classmethod
    def load(cls, folder, split: str = "train", neg_tolerance: float = NEG_TOLERANCE) -> "Scan":
        """Read a clgs scan folder, or an R2-Gaussian dataset folder (``split`` "train" or "test").

        ``folder`` may also be the path of its ``scan.json`` / ``meta_data.json``.
        """
        folder = Path(folder)
        if folder.is_file() and folder.name in (SCAN_JSON, "meta_data.json"):
            folder = folder.parent
        if not folder.exists():
            raise ScanError(f"{folder}: no such scan folder")
        if not folder.is_dir():
            raise ScanError(f"{folder}: a scan is a folder (with scan.json), not a file")
        if (folder / SCAN_JSON).is_file():
            return cls._load_clgs(folder, neg_tolerance)
        from clgs.io import r2gaussian

        if r2gaussian.is_r2gaussian_folder(folder):
            return r2gaussian.read_r2gaussian(folder, split=split, neg_tolerance=neg_tolerance)
        raise ScanError(f"{folder}: not a scan folder: it has neither {SCAN_JSON} (clgs) nor meta_data.json "
                        "(R2-Gaussian)")

    @classmethod
    def _load_clgs(cls, folder: Path, neg_tolerance: float) -> "Scan":
        doc = read_json(folder / SCAN_JSON)
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise ScanError(f"{folder / SCAN_JSON}: not a clgs scan description (format should be {FORMAT!r})")
        version = doc.get("version")
        if not isinstance(version, int) or version > VERSION:
            raise ScanError(f"{folder / SCAN_JSON}: scan format version {version!r} is not supported "
                            f"(this clgs reads up to {VERSION}); update clgs")
        try:
            geometry = Geometry.from_dict(doc["geometry"])
        except (KeyError, TypeError, GeometryError) as exc:
            raise ScanError(f"{folder / SCAN_JSON}: invalid geometry: {exc}") from exc
        files = doc.get("files")
        files = {} if files is None else files
        if not isinstance(files, dict) or not all(isinstance(v, str) or v is None for v in files.values()):
            raise ScanError(f"{folder / SCAN_JSON}: 'files' must map names (projections, truth, truth_surface) "
                            f"to file names in the folder, got {files!r}")
        meta = doc.get("meta") or {}
        if not isinstance(meta, dict):
            raise ScanError(f"{folder / SCAN_JSON}: 'meta' must be an object (key: value), got {meta!r}")
        proj = read_npy(_inside(folder, files.get("projections") or PROJECTIONS, "projections"), "projections")
        with warnings.catch_warnings():
            warnings.simplefilter("always", ScanWarning)
            proj = check_projections(proj, geometry, neg_tolerance, source=str(folder / PROJECTIONS))
        truth = None
        if files.get("truth"):
            truth = _check_truth(read_npy(_inside(folder, files["truth"], "truth"), "truth"), geometry,
                                 str(folder / files["truth"]))
        surface = None
        if files.get("truth_surface"):
            from clgs.io.mesh import MeshError, load_mesh

            try:
                surface = load_mesh(_inside(folder, files["truth_surface"], "truth surface"))
            except MeshError as exc:
                raise ScanError(str(exc)) from exc
        return cls(geometry, proj, truth, meta, surface)


def _inside(folder: Path, name, what: str) -> Path:
    from clgs.io.paths import OutsideFolderError, inside

    try:
        return inside(folder, name, what, SCAN_JSON)
    except OutsideFolderError as exc:
        raise ScanError(str(exc)) from None


def read_json(path: Path):
    """A JSON file, or a ScanError saying it is missing or unreadable."""
    try:
        with open(path, "r", encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise ScanError(f"{path}: missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ScanError(f"{path}: unreadable JSON ({exc})") from exc


def read_npy(path: Path, what: str, named_in: str = "the scan description") -> np.ndarray:
    """An ``.npy`` array (no pickles), or a ScanError saying it is missing or unreadable."""
    if not path.is_file():
        raise ScanError(f"{path}: missing ({what} file named in {named_in})")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any failure means an unreadable array
        reason = str(exc)
        if "pickle" in reason:  # numpy's advice to load it unsafely is never passed on
            reason = "it holds pickled Python objects, which clgs never loads"
        raise ScanError(f"{path}: unreadable {what} array ({reason}); a scan's arrays are plain .npy "
                        "files") from None
