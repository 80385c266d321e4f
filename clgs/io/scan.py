"""The clgs scan folder: projections, scanner geometry and (for simulated scans) the truth.

Layout of a scan folder::

    scan.json            format name and version, Geometry.to_dict(), units, file list, meta
    projections.npy      (n_views, V, U) float32 line integrals
    truth.npy            optional ground truth float32, attenuation in 1/mm, in the input's order
    truth.nii.gz         optional copy of the truth for viewers (affine from the geometry)
    truth_surface.stl    optional true surface, world mm

The truth's files keep the array order of the volume the scan was simulated from
(``geometry.orientation``, e.g. ``"LAS"``; :mod:`clgs.io.orientation`): ``truth.nii.gz`` has the
input's affine and ``truth.npy`` is its array with the axes reversed ((Z, Y, X) for ``"RAS"``).
``Scan.truth`` in memory is always in the working (Z, Y, X) RAS+ order. A scan whose geometry
has another orientation is written as version 2 (older clgs would read its truth.npy in the wrong
order, and refuses it); any other as version 1.

Projections are line integrals ``-log(I / I0)`` of the attenuation ``mu`` (1/mm) along each ray
(lengths in mm), i.e. the units of ``UNITS``; row ``iv`` of a view grows with z and column ``iu``
with the detector's u axis (see :mod:`clgs.geometry`).

``meta`` holds everything else, as JSON: ``acquisition`` (``noise`` true/false, ``I0``,
``sigma``, ``scatter``, ``seed``; ``kev`` when the input was in Hounsfield units), ``provenance``
(what made the scan, with the input's frame and units), optionally ``subject``
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

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clgs.geometry import Geometry, GeometryError
from clgs.io import atomic, r2gaussian
from clgs.io.validate import (  # noqa: F401 - public here
    NEG_TOLERANCE,
    ScanError,
    ScanWarning,
    check_projections,
    inside_folder,
    read_json,
    read_npy,
)

__all__ = ["Scan", "ScanError", "ScanWarning", "FORMAT", "VERSION", "UNITS", "NEG_TOLERANCE",
           "check_projections", "is_scan_folder"]

FORMAT = "clgs-scan"
VERSION = 2
UNITS = "line integral of mu (1/mm) x mm"
TRUTH_UNITS = "1/mm"
SCAN_JSON = "scan.json"
PROJECTIONS = "projections.npy"
TRUTH = "truth.npy"
TRUTH_NIFTI = "truth.nii.gz"
TRUTH_SURFACE = "truth_surface.stl"


def _check_truth(truth, geometry: Geometry, source: str = "truth") -> np.ndarray | None:
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
    truth: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    surface: tuple | None = None

    def __post_init__(self):
        if not isinstance(self.geometry, Geometry):
            raise ScanError(f"geometry must be a clgs.geometry.Geometry, got {type(self.geometry).__name__}")
        self.projections = check_projections(self.projections, self.geometry)
        self.truth = _check_truth(self.truth, self.geometry)
        self.meta = dict(self.meta or {})
        if self.surface is not None:
            from clgs.io.mesh import check_mesh

            v, f = self.surface
            self.surface = check_mesh(v, f)

    @property
    def n_views(self) -> int:
        return int(self.projections.shape[0])

    def subset(self, views: Sequence[int]) -> Scan:
        """The scan restricted to some views (e.g. every 10th for a sparse-view experiment)."""
        idx = np.asarray(views, dtype=int).reshape(-1)
        if idx.size == 0:
            raise ScanError("a subset needs at least one view")
        if idx.min() < -self.n_views or idx.max() >= self.n_views:
            raise ScanError(f"view indices must lie in [0, {self.n_views}), got {idx.tolist()}")
        meta = dict(self.meta)
        meta["views"] = idx.tolist()
        return Scan(self.geometry.select(idx), self.projections[idx],
                    self.truth, meta, self.surface)

    # ------------------------------------------------------------------------------ writing
    def to_json(self) -> dict:
        files = {"projections": PROJECTIONS}
        if self.truth is not None:
            files.update(truth=TRUTH, truth_nifti=TRUTH_NIFTI)
        if self.surface is not None:
            files["truth_surface"] = TRUTH_SURFACE
        doc = {
            "format": FORMAT,
            "version": 1 if self.geometry.orientation == "RAS" else VERSION,
            "units": UNITS,
            "geometry": self.geometry.to_dict(),
            "projections_shape": list(self.projections.shape),
            "files": files,
            "meta": self.meta,
        }
        if self.truth is not None:
            doc["truth_units"] = TRUTH_UNITS
        return doc

    def save(self, folder, overwrite: bool = False, truth_nifti: bool = True) -> Path:
        """Write the scan folder atomically (FileExistsError if it exists and not ``overwrite``)."""
        from clgs.io.orientation import to_file
        from clgs.io.volume import save_volume

        folder = Path(folder)
        doc = self.to_json()
        if not truth_nifti:
            doc["files"].pop("truth_nifti", None)
        with atomic.atomic_dir(folder, overwrite=overwrite) as tmp:
            atomic.save_npy(tmp / PROJECTIONS, self.projections)
            if self.truth is not None:
                atomic.save_npy(tmp / TRUTH, to_file(self.truth, self.geometry.orientation))
                if truth_nifti:
                    save_volume(tmp / TRUTH_NIFTI, self.truth, self.geometry, units=TRUTH_UNITS)
            if self.surface is not None:
                from clgs.io.mesh import save_mesh

                save_mesh(tmp / TRUTH_SURFACE, self.surface.vertices, self.surface.faces)
            atomic.write_json(tmp / SCAN_JSON, doc)
        return folder

    # ------------------------------------------------------------------------------ reading
    @classmethod
    def load(cls, folder, split: str = "train", neg_tolerance: float = NEG_TOLERANCE) -> Scan:
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
        if r2gaussian.is_r2gaussian_folder(folder):
            return read_r2gaussian(folder, split=split, neg_tolerance=neg_tolerance)
        raise ScanError(f"{folder}: not a scan folder: it has neither {SCAN_JSON} (clgs) nor meta_data.json "
                        "(R2-Gaussian)")

    @classmethod
    def _load_clgs(cls, folder: Path, neg_tolerance: float) -> Scan:
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
        proj = read_npy(inside_folder(folder, files.get("projections") or PROJECTIONS, "projections", SCAN_JSON),
                        "projections")
        with warnings.catch_warnings():
            warnings.simplefilter("always", ScanWarning)
            proj = check_projections(proj, geometry, neg_tolerance, source=str(folder / PROJECTIONS))
        truth = None
        if files.get("truth"):
            from clgs.io.orientation import to_working

            stored = read_npy(inside_folder(folder, files["truth"], "truth", SCAN_JSON), "truth")
            if np.ndim(stored) == 3 and geometry.orientation != "RAS":  # the file's order -> the working order
                stored = to_working(stored, geometry.orientation)
            truth = _check_truth(stored, geometry, str(folder / files["truth"]))
        surface = None
        if files.get("truth_surface"):
            from clgs.io.mesh import MeshError, load_mesh

            try:
                # clgs's own file: tagged; an untagged one is read as RAS, as clgs wrote it before the tag
                surface = load_mesh(inside_folder(folder, files["truth_surface"], "truth surface", SCAN_JSON),
                                    space="RAS")
            except MeshError as exc:
                raise ScanError(str(exc)) from exc
        return cls(geometry, proj, truth, meta, surface)


def read_r2gaussian(folder, split: str = "train", neg_tolerance: float = NEG_TOLERANCE) -> Scan:
    """An R2-Gaussian dataset folder as a :class:`Scan` (views of ``split``: train or test); see
    :func:`clgs.io.r2gaussian.read_parts`."""
    return Scan(*r2gaussian.read_parts(folder, split=split, neg_tolerance=neg_tolerance))
