"""The checks every scan reader applies (clgs and R2-Gaussian folders, arrays handed to a
reconstruction): projections against their geometry, and JSON / ``.npy`` files read safely."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from clgs.errors import ClgsError
from clgs.geometry import Geometry

NEG_TOLERANCE = 0.05  # of the largest line integral: smaller negatives are noise, set to 0


class ScanError(ClgsError, ValueError):
    """A scan that cannot be used: missing files, mismatched shapes, impossible values."""


class ScanWarning(UserWarning):
    """Something was repaired while reading a scan (e.g. tiny negative line integrals set to 0)."""


def check_projections(projections, geometry: Geometry, neg_tolerance: float | None = NEG_TOLERANCE,
                      source: str = "projections") -> np.ndarray:
    """Validate line integrals against a geometry; return them as float32 (tiny negatives -> 0).

    Errors name what is wrong and what to do: wrong rank, zero views, shape not matching
    (n_views, nDetector), NaN/Inf, line integrals below ``-neg_tolerance * max``.
    ``neg_tolerance=None`` (a reconstruction given arrays, not a scan): only the shape and
    finiteness checks, and the array comes back as it is (its dtype kept, no copy).
    """
    if not isinstance(geometry, Geometry):
        raise TypeError(f"{source} needs a clgs.geometry.Geometry, got {type(geometry).__name__}")
    p = np.asarray(projections)
    if p.dtype == object or not np.issubdtype(p.dtype, np.number) or np.issubdtype(p.dtype, np.complexfloating):
        raise ScanError(f"{source}: not an array of real numbers (dtype {p.dtype}); line integrals are real")
    if p.ndim != 3:
        raise ScanError(f"{source}: expected (n_views, V, U) line integrals, got an array of shape {p.shape}")
    if p.shape[0] == 0:
        raise ScanError(f"{source}: the scan has zero views; a reconstruction needs at least one view")
    expected = (geometry.n_views, *geometry.nDetector)
    if tuple(p.shape) != expected:
        raise ScanError(
            f"{source}: shape {tuple(p.shape)} does not match the geometry, which expects (n_views, V, U) = "
            f"{expected}; "
            "check nDetector (V, U order) and the number of views (angles or vectors)")
    if neg_tolerance is not None:
        p = p.astype(np.float32, copy=True)
    bad = ~np.isfinite(p)
    if bad.any():
        views = np.unique(np.nonzero(bad)[0])
        raise ScanError(f"{source}: {int(bad.sum())} values are NaN or Inf (views {views[:10].tolist()}"
                        f"{'...' if views.size > 10 else ''}); the projections are corrupted")
    lo = float(p.min())
    if lo < 0 and neg_tolerance is not None:
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



def read_json(path: Path):
    """A JSON file, or a ScanError saying it is missing or unreadable."""
    try:
        with open(path, encoding="utf-8") as fh:
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


def inside_folder(folder: Path, name, what: str, described_in: str) -> Path:
    """``folder / name`` if it stays inside ``folder`` (:func:`clgs.io.paths.inside`), else a ScanError."""
    from clgs.io.paths import OutsideFolderError, inside

    try:
        return inside(folder, name, what, described_in)
    except OutsideFolderError as exc:
        raise ScanError(str(exc)) from None
