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
object). Then, by default, each view's I0 is set from its own air (:mod:`clgs.io.air`): the air
reads 0 whatever the beam did between the flat fields and the projections, and the background
removed is reported per view. Ratios at or below a floor (dead pixels, photon starvation) are set
to the floor and counted; line integrals still below 0 (noise in the air) are set to 0 and
counted too. Zingers (:mod:`clgs.io.artefacts`) are removed on request before the air is
measured; sinogram stripes (rings) after it, before the clipping.

HDF5 files are read as Data Exchange (``exchange/data``) or NeXus NXtomo (:mod:`clgs.io.nexus`).

:func:`find_centre` finds the column the rotation axis projects to with every estimator of
:mod:`clgs.io.axis` (a 180-degree pair, a sinogram sharpness search, the centre of mass after the
air background is removed), and reports each one's figure and how far they agree; the pair also
gives the detector's roll, applied through per-view vectors on request.
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
            images = [_read_tiff(p)[0] for p in tiffs]
            return _stack(images, str(path), [p.name for p in tiffs])
        if dicoms:
            from clgs.io.dicom_series import series_in, several_series_message

            series = series_in(path)
            if len(series) > 1:
                raise RawError(several_series_message(path, series))
            return _stack([_read_dicom_image(p) for p in dicoms], str(path), [p.name for p in dicoms])
        raise RawError(f"{path}: a folder with neither .tif/.tiff nor .dcm images")
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        return _read_tiff(path)
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


def _read_tiff(path) -> np.ndarray:
    """One TIFF file (a page or a stack) as views; a damaged or truncated file is named."""
    import tifffile

    try:
        return _as_views(tifffile.imread(str(path)), path)
    except RawError:
        raise
    except Exception as exc:  # noqa: BLE001 - tifffile's own message says what it could not read
        why = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise RawError(f"{path}: not a readable TIFF, perhaps truncated or damaged ({why}); "
                       "replace or remove this file") from exc


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


def _read_hdf5(path: Path) -> RawProjections:
    """Data Exchange or NXtomo, whichever the file holds."""
    try:
        import h5py
    except ImportError as exc:
        raise RawError("HDF5 files need h5py: pip install 'clgs[formats]' (the set-up installs it)") from exc
    from clgs.io.nexus import angle_values, is_nxtomo, read_nxtomo

    try:
        with h5py.File(path, "r") as f:
            if "exchange/data" not in f:
                if not is_nxtomo(f):
                    raise RawError(f"{path}: neither the Data Exchange layout ('exchange/data') nor NeXus NXtomo "
                                   "(an NXentry with an NXdetector holding 'data'); export the projections as "
                                   "TIFF or .npy instead")
                try:
                    nx = read_nxtomo(f, path)
                except ValueError as exc:
                    raise RawError(str(exc)) from None
                data = _as_views(nx["data"], f"{path}:projections")
                flats = None if nx["flats"] is None else _as_views(nx["flats"], f"{path}:flats")
                darks = None if nx["darks"] is None else _as_views(nx["darks"], f"{path}:darks")
                return RawProjections(data, flats, darks, nx["angles_deg"], str(path),
                                      [nx["layout"], *nx["notes"]])
            data = _as_views(f["exchange/data"][()], f"{path}:exchange/data")
            flats = _as_views(f["exchange/data_white"][()], f"{path}:exchange/data_white") \
                if "exchange/data_white" in f else None
            darks = _as_views(f["exchange/data_dark"][()], f"{path}:exchange/data_dark") \
                if "exchange/data_dark" in f else None
            try:
                theta = angle_values(f["exchange/theta"], f"{path}:exchange/theta") if "exchange/theta" in f else None
            except ValueError as exc:
                raise RawError(str(exc)) from None
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
        raw = _read_hdf5(path)
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


def line_integrals(raw: RawProjections, air_columns=None, floor: float = DEFAULT_FLOOR, air: bool = True,
                   zingers=None, rings=None):
    """(line integrals (n_views, rows, columns) float32, report dict): ``-log`` of the flat- and
    dark-corrected counts. ``air_columns`` (first, last exclusive) names detector columns that see
    only air (found per view when None). ``air``: set each view's I0 from its air so that the air
    reads 0 (:func:`clgs.io.air.normalise_air`). ``zingers``: None, ``"auto"`` or a threshold
    (:func:`clgs.io.artefacts.remove_zingers`). ``rings``: None or the stripe filter's size in
    columns (:func:`clgs.io.artefacts.remove_stripes`), before negative values are set to 0 (a
    stripe clipped in the air and kept in the object is no longer a stripe)."""
    from clgs.io.air import normalise_air
    from clgs.io.artefacts import remove_stripes, remove_zingers

    if not (0 < floor < 1):
        raise RawError(f"the floor must lie in (0, 1), got {floor}")
    data = np.asarray(raw.data, np.float64)
    if not np.all(np.isfinite(data)):
        raise RawError(f"{raw.source}: the projections hold NaN or Inf counts")
    dark = np.zeros(data.shape[1:]) if raw.darks is None else np.asarray(raw.darks, np.float64).mean(0)
    report = {"views": int(data.shape[0]), "flats": 0 if raw.flats is None else int(len(raw.flats)),
              "darks": 0 if raw.darks is None else int(len(raw.darks))}
    if raw.notes:
        report["notes"] = list(raw.notes)
    if air_columns is not None:
        a, b = (int(v) for v in air_columns)
        if not (0 <= a < b <= data.shape[2]):
            raise RawError(f"air columns {a}:{b} lie outside the detector's 0:{data.shape[2]}")
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
    _check_floored(raw.source, starved, floor, report)
    ratio = np.where(starved, floor, ratio)
    proj = -np.log(ratio)
    if zingers is not None:
        try:
            proj, report["zingers"] = remove_zingers(proj, zingers)
        except ValueError as exc:
            raise RawError(str(exc)) from None
        proj = np.asarray(proj, np.float64)
    if air:
        try:
            proj, report["air"] = normalise_air(proj, air_columns)
        except ValueError as exc:
            report["air"] = {"air": "none", "note": f"not normalised: {exc}; give --air-columns"}
    if rings is not None:
        try:
            proj, report["rings"] = remove_stripes(proj, rings)
        except ValueError as exc:
            raise RawError(str(exc)) from None
    # still below 0 (noise in the air, a beam brighter than the flat field without air
    # normalisation): no negative attenuation exists, so these are set to 0 and counted
    negative = proj < 0
    report["brighter_than_flat_pixels"] = int(np.count_nonzero(negative))
    report["most_negative"] = float(proj.min()) if negative.any() else 0.0
    proj = np.where(negative, 0.0, proj)
    return np.asarray(proj, np.float32), report


#: above this share of floored pixels the images are probably not raw counts
FLOORED_WARNING = 0.5
NOT_COUNTS_HINT = ("line integrals (already -log) or attenuation images are no raw counts: write them as a scan "
                   "folder (projections.npy and scan.json, docs/formats.md; in Python clgs.io.scan.Scan(geometry, "
                   "projections).save(folder)) instead of clgs import")


def _check_floored(source, starved, floor, report) -> None:
    """Refuse images whose every pixel is at the floor (black, or not counts); put a warning in
    ``report["floored_warning"]`` when more than half are: counts have air or the object's
    transmission in most pixels, line integrals have 0 in the air."""
    if starved.all():
        raise RawError(f"{source}: every pixel is at or below the floor ({floor:g} of the beam): the images are "
                       "black (no counts above the dark field) or hold no raw counts; "
                       f"check the files (and --flats/--darks); {NOT_COUNTS_HINT}")
    if starved.mean() > FLOORED_WARNING:
        report["floored_warning"] = (
            f"{source}: {starved.mean():.0%} of the pixels are at or below the floor ({floor:g} of the beam): do "
            f"these images hold raw counts? {NOT_COUNTS_HINT}")


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


def find_centre(proj: np.ndarray, angles_rad, mode: str = "parallel") -> tuple[float, dict]:
    """(column of the rotation axis at the middle row, report) from every estimator of
    :func:`clgs.io.axis.find_axis` (the report holds each one's column and figure, their spread,
    ``agree``, ``warning`` when they disagree, and ``tilt_deg``)."""
    from clgs.io.axis import AxisError, find_axis

    try:
        column, tilt, report = find_axis(proj, angles_rad, mode)
    except AxisError as exc:
        raise RawError(str(exc)) from None
    report["tilt_deg"] = tilt
    return column, report


def _rolled(geometry, column: float, roll_deg: float):
    """``geometry`` (circular) as per-view vectors with the detector turned by ``roll_deg`` in its
    plane (u towards v), the axis still meeting the middle row at ``column``."""
    from clgs.geometry import Geometry

    vec = geometry.frame_vectors()
    g = np.deg2rad(float(roll_deg))
    dv, du = geometry.dDetector
    e_u, e_v = vec[:, 6:9] / du, vec[:, 9:12] / dv
    nU = geometry.nDetector[1]
    vec[:, 3:6] += (((nU - 1) / 2.0 - column) * du * np.cos(g) - geometry.offDetector[1]) * e_u
    vec[:, 6:9] = du * (np.cos(g) * e_u + np.sin(g) * e_v)
    vec[:, 9:12] = dv * (-np.sin(g) * e_u + np.cos(g) * e_v)
    return Geometry.from_vectors(vec, geometry.nDetector, geometry.nVoxel, geometry.dVoxel, geometry.offOrigin,
                                 geometry.mode, geometry.isocentre)


def scan_from_raw(raw: RawProjections, *, mode: str = "parallel", pixel: float = 1.0, DSO: float | None = None,
                  DSD: float | None = None, angles_deg=None, arc_deg: float | None = None, centre="auto",
                  crop=None, binning=(1, 1), air_columns=None, floor: float = DEFAULT_FLOOR, views=None,
                  geometry=None, air: bool = True, tilt=None, rings=None, zingers=None):
    """(clgs Scan, report) from raw counts: line integrals (:func:`line_integrals`), crop and bin,
    the angles (``angles_deg`` (n_views,), else the file's, else ``arc_deg`` evenly spaced with the
    last view one step short of the end), the rotation axis (``centre``: ``"auto"``
    (:func:`find_centre`), a column number in the cropped and binned detector, or None for the
    middle column), and a circular geometry in TIGRE's terms: the axis column becomes
    ``offDetector``; the volume is the detector's rows high and its width across (voxels of
    one pixel over the magnification). ``views``: keep this many evenly spaced views (after the
    centre is found on all of them). ``geometry``: a geometry file (:func:`clgs.geometry.read_geometry`:
    TIGRE's names or per-view vectors) that describes the detector after crop and binning; it
    replaces the angles, centre, mode and distances. ``air``, ``zingers``: as for
    :func:`line_integrals`, as is ``rings`` (a stripe filter's size in columns). ``tilt``: None (the roll
    is estimated and reported, not applied), ``"auto"`` (the estimate applied) or degrees: a
    rolled detector is written as per-view vectors."""
    from clgs.geometry import Geometry, GeometryError
    from clgs.io.scan import Scan

    if geometry is not None:
        return _scan_with_geometry(raw, geometry, crop, binning, air_columns, floor, views, air, rings, zingers)
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
    proj, report = _corrected(raw, crop, binning, air_columns, floor, air, rings, zingers)
    bu = int(binning[1])
    d_det = float(pixel) * bu
    theta = np.deg2rad(angles)
    nV, nU = proj.shape[1:]
    estimated_tilt = None
    if isinstance(centre, str) and centre == "auto":
        column, centre_report = find_centre(proj, theta, mode)
        estimated_tilt = centre_report.pop("tilt_deg")
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
    d_row = float(pixel) * int(binning[0])
    if estimated_tilt is not None:  # pixels (columns per row) to the detector's physical roll
        estimated_tilt = float(np.rad2deg(np.arctan(np.tan(np.deg2rad(estimated_tilt)) * d_det / d_row)))
    report["tilt"] = {"estimated_deg": estimated_tilt, "applied_deg": None,
                      "from": "180-degree pair" if estimated_tilt is not None else None}
    if tilt is not None:
        if isinstance(tilt, str):
            if tilt != "auto":
                raise RawError(f"tilt must be 'auto' or degrees, got {tilt!r}")
            if estimated_tilt is None:
                raise RawError("the detector's roll cannot be estimated here (it needs the axis found with "
                               "--centre auto from a parallel-beam scan with two views 180 degrees apart and four "
                               "rows or more); give it in degrees (--tilt DEG)")
            report["tilt"]["applied_deg"] = estimated_tilt
        else:
            if not (np.isfinite(float(tilt)) and abs(float(tilt)) < 45):
                raise RawError(f"the tilt must be a number of degrees within (-45, 45), got {tilt}")
            report["tilt"]["applied_deg"] = float(tilt)
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
        if report["tilt"]["applied_deg"]:
            geometry = _rolled(geometry, column, report["tilt"]["applied_deg"])
    except GeometryError as exc:
        raise RawError(f"the scanner geometry is invalid: {exc}") from exc
    meta = {"acquisition": {"noise": True, "real": True}, "provenance": {"source": raw.source, "import": report}}
    return Scan(geometry, proj, None, meta), report


def _corrected(raw, crop, binning, air_columns, floor, air, rings, zingers):
    """(line integrals (:func:`line_integrals`) after crop and binning, report)."""
    proj, report = line_integrals(raw, air_columns, floor, air=air, zingers=zingers, rings=rings)
    return crop_and_bin(proj, crop, binning), report


def _scan_with_geometry(raw, path, crop, binning, air_columns, floor, views, air=True, rings=None, zingers=None):
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
    proj, report = _corrected(raw, crop, binning, air_columns, floor, air, rings, zingers)
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
