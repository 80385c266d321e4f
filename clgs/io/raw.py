"""Raw detector images into line integrals: reading, flat and dark fields, -log, crop and bin,
and finding the rotation centre.

What a scanner or a beamline writes is photon counts, not line integrals. :func:`read_raw`
reads them from an HDF5 Data Exchange file (``exchange/data``, ``data_white``, ``data_dark``,
``theta`` in degrees: the layout tomography beamlines write), a TIFF stack (one multi-page file
or a folder of single images, in name order), a DICOM series of projection images (a folder or
one file of it, through SimpleITK) or a ``.npy`` array (n_views, rows, columns). Flat and dark
fields may sit in the same file (Data Exchange) or be given as files of the same kinds; several
of each are averaged.

:func:`line_integrals` turns counts into ``-log((I - dark) / (flat - dark))``. Without flat
fields the unattenuated intensity I0 is estimated per view from an air region (given columns, or
by default the brightest 1 % of each view's pixels, which assumes some of each view sees past the
object). Ratios at or below a floor (dead pixels, photon starvation) are set to the floor and
counted; the count is reported. Line integrals below 0 (brighter than the flat field: noise, or
the beam drifting between the flat fields and the projections) are set to 0 and counted too.

:func:`find_centre` estimates the column the rotation axis projects to, for a parallel or a
circular cone-beam scan, by the centre-of-mass method: the attenuation-weighted mean column of
each view follows ``c0 + a cos(theta) + b sin(theta)`` around the axis, so a least-squares fit
over the views gives ``c0``. It needs views spread over at least about 90 degrees and an object
that stays on the detector (truncated views bias it).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clgs.errors import ClgsError

__all__ = ["RawError", "RawProjections", "read_raw", "read_images", "line_integrals", "crop_and_bin",
           "find_centre", "RAW_SUFFIXES"]

RAW_SUFFIXES = (".h5", ".hdf5", ".hdf", ".nxs", ".cxi", ".tif", ".tiff", ".dcm", ".npy")
DEFAULT_FLOOR = 1e-6


class RawError(ClgsError, ValueError):
    """Raw images that cannot be turned into line integrals as asked."""


@dataclass
class RawProjections:
    """Counts (n_views, rows, columns) float32, with what came with them."""

    data: np.ndarray
    flats: np.ndarray | None = None
    darks: np.ndarray | None = None
    angles_deg: np.ndarray | None = None
    source: str = ""
    notes: list = field(default_factory=list)


def _stack(arrays, what: str, names) -> np.ndarray:
    shapes = {tuple(a.shape) for a in arrays}
    if len(shapes) > 1:
        first = tuple(arrays[0].shape)
        bad = next(n for n, a in zip(names, arrays) if tuple(a.shape) != first)
        raise RawError(f"{what}: images of different sizes ({names[0]} is {first}, {bad} is "
                       f"{tuple(next(a for n, a in zip(names, arrays) if n == bad).shape)}); give images of one size")
    return np.stack(arrays).astype(np.float32)


def _as_views(arr: np.ndarray, path) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise RawError(f"{path}: not an array of real numbers (dtype {arr.dtype})")
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise RawError(f"{path}: expected images (n, rows, columns), got an array of shape {arr.shape}")
    if arr.shape[0] == 0 or min(arr.shape[1:]) == 0:
        raise RawError(f"{path}: holds no image (shape {arr.shape})")
    return arr.astype(np.float32)


def read_images(path) -> np.ndarray:
    """Images (n, rows, columns) float32 from a TIFF stack or folder of TIFFs, a DICOM file or
    series, or a ``.npy`` array."""
    path = Path(path)
    if not path.exists():
        raise RawError(f"{path}: no such file or folder")
    if path.is_dir():
        tiffs = sorted(p for p in path.iterdir() if p.suffix.lower() in (".tif", ".tiff"))
        dicoms = sorted(p for p in path.iterdir() if p.suffix.lower() == ".dcm")
        if tiffs:
            import tifffile

            images = [_as_views(tifffile.imread(str(p)), p)[0] for p in tiffs]
            return _stack(images, str(path), [p.name for p in tiffs])
        if dicoms:
            return _stack([_read_dicom_image(p) for p in dicoms], str(path), [p.name for p in dicoms])
        raise RawError(f"{path}: a folder with neither .tif/.tiff nor .dcm images")
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        import tifffile

        try:
            return _as_views(tifffile.imread(str(path)), path)
        except RawError:
            raise
        except Exception as exc:  # noqa: BLE001 - tifffile's own message says what it could not read
            raise RawError(f"{path}: not a readable TIFF ({exc})") from exc
    if suffix == ".dcm":
        return _read_dicom_image(path)[None]
    if suffix == ".npy":
        try:
            return _as_views(np.load(path, allow_pickle=False), path)
        except RawError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise RawError(f"{path}: not a readable .npy array ({exc})") from exc
    raise RawError(f"{path}: unknown image format; use HDF5 Data Exchange, TIFF, DICOM or .npy")


def _read_dicom_image(path) -> np.ndarray:
    try:
        import SimpleITK as sitk
    except ImportError as exc:
        raise RawError("DICOM images need SimpleITK: pip install 'clgs[formats]' (the set-up installs it)") from exc
    try:
        arr = sitk.GetArrayFromImage(sitk.ReadImage(str(path)))
    except Exception as exc:  # noqa: BLE001
        raise RawError(f"{path}: not a readable DICOM image ({str(exc).strip().splitlines()[-1]})") from exc
    arr = np.asarray(arr, np.float32)
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2:
        raise RawError(f"{path}: expected one 2-D projection image, got an array of shape {arr.shape}")
    return arr


def _read_data_exchange(path: Path) -> RawProjections:
    try:
        import h5py
    except ImportError as exc:
        raise RawError("HDF5 files need h5py: pip install 'clgs[formats]' (the set-up installs it)") from exc
    try:
        with h5py.File(path, "r") as f:
            if "exchange/data" not in f:
                raise RawError(f"{path}: no 'exchange/data' dataset (not the Data Exchange layout); "
                               "export the projections as TIFF or .npy instead")
            data = _as_views(f["exchange/data"][()], f"{path}:exchange/data")
            flats = _as_views(f["exchange/data_white"][()], f"{path}:exchange/data_white") \
                if "exchange/data_white" in f else None
            darks = _as_views(f["exchange/data_dark"][()], f"{path}:exchange/data_dark") \
                if "exchange/data_dark" in f else None
            theta = np.asarray(f["exchange/theta"][()], np.float64).reshape(-1) if "exchange/theta" in f else None
    except RawError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise RawError(f"{path}: not a readable HDF5 file ({exc})") from exc
    return RawProjections(data, flats, darks, theta, str(path))


def read_raw(path, flats=None, darks=None) -> RawProjections:
    """Counts and their flat and dark fields (see the module doc). ``flats`` / ``darks``: files or
    folders of images, which replace any stored with the data."""
    path = Path(path)
    if path.suffix.lower() in (".h5", ".hdf5", ".hdf", ".nxs", ".cxi"):
        if not path.is_file():
            raise RawError(f"{path}: no such file")
        raw = _read_data_exchange(path)
    else:
        raw = RawProjections(read_images(path), source=str(path))
    if flats is not None:
        raw.flats = read_images(flats)
    if darks is not None:
        raw.darks = read_images(darks)
    for what, arr in (("flat", raw.flats), ("dark", raw.darks)):
        if arr is not None and tuple(arr.shape[1:]) != tuple(raw.data.shape[1:]):
            raise RawError(f"{what} fields are {arr.shape[1]} x {arr.shape[2]} pixels, the projections "
                           f"{raw.data.shape[1]} x {raw.data.shape[2]}; they must match")
    return raw


def line_integrals(raw: RawProjections, air_columns=None, floor: float = DEFAULT_FLOOR):
    """(line integrals (n_views, rows, columns) float32, report dict): ``-log`` of the flat- and
    dark-corrected counts. ``air_columns`` (first, last) names detector columns that see only air,
    for I0 when there are no flat fields."""
    if not (0 < floor < 1):
        raise RawError(f"the floor must lie in (0, 1), got {floor}")
    data = np.asarray(raw.data, np.float64)
    if not np.all(np.isfinite(data)):
        raise RawError(f"{raw.source}: the projections hold NaN or Inf counts")
    dark = np.zeros(data.shape[1:]) if raw.darks is None else np.asarray(raw.darks, np.float64).mean(0)
    report = {"views": int(data.shape[0]), "flats": 0 if raw.flats is None else int(len(raw.flats)),
              "darks": 0 if raw.darks is None else int(len(raw.darks))}
    if raw.flats is not None:
        flat = np.asarray(raw.flats, np.float64).mean(0)
        below = int(np.count_nonzero(flat <= dark))
        if below == flat.size:
            raise RawError(f"{raw.source}: the flat field is darker than (or equal to) its dark field at every "
                           "pixel: the two are swapped or the beam was off")
        if below:
            report["flat_not_above_dark_pixels"] = below  # treated as dead pixels: floored below
        ratio = (data - dark) / np.where(flat > dark, flat - dark, np.inf)
        report["I0"] = "flat fields"
    else:
        signal = data - dark
        if air_columns is not None:
            a, b = (int(v) for v in air_columns)
            if not (0 <= a < b <= data.shape[2]):
                raise RawError(f"air columns {air_columns} lie outside the detector's 0..{data.shape[2]}")
            i0 = signal[:, :, a:b].mean(axis=(1, 2))
            report["I0"] = f"air columns {a}-{b - 1}"
        else:
            flat_views = signal.reshape(len(signal), -1)
            k = max(1, flat_views.shape[1] // 100)
            i0 = np.sort(flat_views, axis=1)[:, -k:].mean(1)  # the brightest 1 % of each view
            report["I0"] = "brightest 1 % of each view"
        if np.any(i0 <= 0):
            raise RawError(f"{raw.source}: no positive air intensity in views "
                           f"{np.nonzero(i0 <= 0)[0][:10].tolist()}; give flat fields")
        ratio = signal / i0[:, None, None]
    starved = ~(ratio > floor)  # NaN, zero, negative, or below the floor
    report["floored_pixels"] = int(np.count_nonzero(starved))
    report["floored_fraction"] = float(starved.mean())
    ratio = np.where(starved, floor, ratio)
    proj = -np.log(ratio)
    # brighter than the flat field (noise, beam drift between flat and projection): no negative
    # attenuation exists, so these are set to 0 and counted
    negative = proj < 0
    report["brighter_than_flat_pixels"] = int(np.count_nonzero(negative))
    report["most_negative"] = float(proj.min()) if negative.any() else 0.0
    proj[negative] = 0.0
    return proj.astype(np.float32), report


def crop_and_bin(proj: np.ndarray, crop=None, binning=(1, 1)) -> np.ndarray:
    """``proj`` (n, rows, columns) cropped to rows ``crop[0]:crop[1]`` and columns
    ``crop[2]:crop[3]``, then averaged over blocks of ``binning`` (rows, columns) pixels."""
    p = np.asarray(proj)
    if crop is not None:
        r0, r1, c0, c1 = (int(v) for v in crop)
        if not (0 <= r0 < r1 <= p.shape[1] and 0 <= c0 < c1 <= p.shape[2]):
            raise RawError(f"crop {crop} lies outside the {p.shape[1]} x {p.shape[2]} detector")
        p = p[:, r0:r1, c0:c1]
    bv, bu = (int(v) for v in binning)
    if bv < 1 or bu < 1:
        raise RawError(f"binning must be whole numbers >= 1, got {binning}")
    if bv > p.shape[1] or bu > p.shape[2]:
        raise RawError(f"binning {bv} x {bu} is larger than the {p.shape[1]} x {p.shape[2]} detector")
    if (bv, bu) != (1, 1):
        nv, nu = p.shape[1] // bv, p.shape[2] // bu
        p = p[:, :nv * bv, :nu * bu].reshape(p.shape[0], nv, bv, nu, bu).mean(axis=(2, 4))
    return np.ascontiguousarray(p, np.float32)


def find_centre(proj: np.ndarray, angles_rad) -> tuple[float, dict]:
    """(column of the rotation axis, report) by the centre-of-mass fit of the module doc.

    ``proj`` (n_views, rows, columns) line integrals; ``angles_rad`` (n_views,)."""
    p = np.clip(np.asarray(proj, np.float64), 0.0, None)
    theta = np.asarray(angles_rad, np.float64).reshape(-1)
    if theta.size != p.shape[0]:
        raise RawError(f"{theta.size} angles for {p.shape[0]} views")
    span = float(np.ptp(np.unwrap(theta))) if theta.size > 1 else 0.0
    if theta.size < 3 or span < np.pi / 2:
        raise RawError("finding the centre needs at least 3 views over at least 90 degrees; "
                       "give the centre (--centre) instead")
    mass = p.sum(axis=(1, 2))
    if np.any(mass <= 0):
        raise RawError("a view holds no attenuation: the centre cannot be found from it; give --centre")
    cols = np.arange(p.shape[2], dtype=np.float64)
    com = (p.sum(axis=1) * cols).sum(axis=1) / mass
    A = np.stack([np.ones_like(theta), np.cos(theta), np.sin(theta)], axis=1)
    coef, *_ = np.linalg.lstsq(A, com, rcond=None)
    resid = com - A @ coef
    report = {"method": "centre of mass, fitted sinusoid", "views": int(theta.size),
              "rms_residual_pixels": float(np.sqrt(np.mean(resid ** 2))),
              "amplitude_pixels": float(np.hypot(coef[1], coef[2]))}
    return float(coef[0]), report


def scan_from_raw(raw: RawProjections, *, mode: str = "parallel", pixel: float = 1.0, DSO: float | None = None,
                  DSD: float | None = None, angles_deg=None, arc_deg: float | None = None, centre="auto",
                  crop=None, binning=(1, 1), air_columns=None, floor: float = DEFAULT_FLOOR, views=None,
                  geometry=None):
    """(clgs Scan, report) from raw counts: line integrals (:func:`line_integrals`), crop and bin,
    the angles (``angles_deg`` (n_views,), else the file's, else ``arc_deg`` evenly spaced with the
    last view one step short of the end), the rotation axis (``centre``: ``"auto"``
    (:func:`find_centre`), a column number in the cropped and binned detector, or None for the
    middle column), and a circular geometry in TIGRE's terms: the axis column becomes
    ``offDetector``; the volume is the detector's rows high and its width across (voxels of
    one pixel over the magnification). ``views``: keep this many evenly spaced views (after the
    centre is found on all of them). ``geometry``: a geometry file (:func:`clgs.geometry.read_geometry`:
    TIGRE's names or per-view vectors) that describes the detector after crop and binning; it
    replaces the angles, centre, mode and distances."""
    from clgs.geometry import Geometry, GeometryError
    from clgs.io.scan import Scan

    if geometry is not None:
        return _scan_with_geometry(raw, geometry, crop, binning, air_columns, floor, views)
    if mode not in ("parallel", "cone"):
        raise RawError(f"mode must be 'parallel' or 'cone', got {mode!r}")
    if not (np.isfinite(pixel) and pixel > 0):
        raise RawError(f"the pixel size must be a positive number of mm, got {pixel}")
    n = raw.data.shape[0]
    if angles_deg is not None:
        angles = np.asarray(angles_deg, np.float64).reshape(-1)
        source_of_angles = "given"
    elif raw.angles_deg is not None:
        angles = np.asarray(raw.angles_deg, np.float64).reshape(-1)
        source_of_angles = "the file"
    elif arc_deg is not None:
        angles = np.arange(n) * (float(arc_deg) / n)
        source_of_angles = f"{arc_deg:g} degrees evenly spaced"
    else:
        raise RawError(f"{raw.source}: the file holds no angles; give them (a file of one angle per view, in "
                       "degrees) or the arc they span")
    if angles.size != n:
        raise RawError(f"{angles.size} angles for {n} projections ({source_of_angles}); give one angle per view")
    if not np.all(np.isfinite(angles)):
        raise RawError("the angles hold NaN or Inf")
    proj, report = line_integrals(raw, air_columns, floor)
    proj = crop_and_bin(proj, crop, binning)
    bu = int(binning[1])
    d_det = float(pixel) * bu
    theta = np.deg2rad(angles)
    nV, nU = proj.shape[1:]
    if isinstance(centre, str) and centre == "auto":
        column, centre_report = find_centre(proj, theta)
        report["centre"] = {"column": column, **centre_report}
    elif centre is None:
        column = (nU - 1) / 2.0
        report["centre"] = {"column": column, "method": "the middle column (assumed)"}
    else:
        column = float(centre)
        if not (0 <= column <= nU - 1):
            raise RawError(f"the centre column {column} lies outside the detector's 0..{nU - 1}")
        report["centre"] = {"column": column, "method": "given"}
    off_u = ((nU - 1) / 2.0 - column) * d_det
    if mode == "cone":
        if DSO is None or DSD is None:
            raise RawError("a cone-beam scan needs DSO and DSD (mm)")
        mag = float(DSD) / float(DSO)
    else:
        DSO, DSD, mag = 1000.0, 1500.0, 1.0  # not used by parallel beam
    vox = d_det / mag
    if views is not None:
        k = int(views)
        if not 1 <= k <= n:
            raise RawError(f"views must lie in 1..{n}, got {k}")
        keep = np.linspace(0, n, k, endpoint=False).astype(int)
        proj, theta = proj[keep], theta[keep]
        report["views_kept"] = keep.tolist()
    report["angles"] = source_of_angles
    try:
        geometry = Geometry(mode=mode, DSD=float(DSD), DSO=float(DSO), nDetector=(nV, nU),
                            dDetector=(float(pixel) * int(binning[0]), d_det),
                            nVoxel=(nV, nU, nU), dVoxel=(float(pixel) * int(binning[0]) / mag, vox, vox),
                            offDetector=(0.0, off_u), angles=theta)
    except GeometryError as exc:
        raise RawError(f"the scanner geometry is invalid: {exc}") from exc
    meta = {"acquisition": {"noise": True, "real": True}, "provenance": {"source": raw.source, "import": report}}
    return Scan(geometry, proj, None, meta), report


def _scan_with_geometry(raw, path, crop, binning, air_columns, floor, views):
    """(Scan, report) of :func:`scan_from_raw` with the whole geometry from the file ``path``."""
    from clgs.geometry import GeometryError, read_geometry
    from clgs.io.scan import Scan

    try:
        geometry = read_geometry(path)
    except GeometryError as exc:
        raise RawError(str(exc)) from None
    n = raw.data.shape[0]
    if geometry.n_views != n:
        raise RawError(f"{path}: the geometry has {geometry.n_views} views but {raw.source} holds {n} "
                       "projections; give one view per projection")
    proj, report = line_integrals(raw, air_columns, floor)
    proj = crop_and_bin(proj, crop, binning)
    if tuple(proj.shape[1:]) != tuple(geometry.nDetector):
        raise RawError(f"{path}: nDetector {list(geometry.nDetector)} (rows, columns) differs from the images' "
                       f"{list(proj.shape[1:])} after crop and binning; describe the detector as imported")
    report["angles"] = f"the geometry file {path}"
    report["centre"] = {"column": None, "method": f"the geometry file {path}"}
    scan = Scan(geometry, proj, None, {"acquisition": {"noise": True, "real": True},
                                       "provenance": {"source": raw.source, "import": report}})
    if views is not None:
        k = int(views)
        if not 1 <= k <= n:
            raise RawError(f"views must lie in 1..{n}, got {k}")
        keep = np.linspace(0, n, k, endpoint=False).astype(int)
        scan = scan.subset(keep)
        scan.meta["provenance"]["import"]["views_kept"] = keep.tolist()
    return scan, report
