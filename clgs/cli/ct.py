"""``clgs simulate``, ``clgs reconstruct``, ``clgs evaluate``: the generic CT command line.

Only click and the standard library are imported at module level, so ``clgs --help`` stays fast;
NumPy, the OpenCL kernels and the methods load when a command runs. Every output is written
atomically (a temporary sibling renamed into place); an existing output needs ``--force``.
"""
from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import click

from clgs.cli.options import FiniteFloat, Seed, check_option_values, method_params

VOLUME_SUFFIXES = (".npy", ".nii", ".nii.gz")


def _is_volume_path(path: Path) -> bool:
    name = path.name.lower()
    return any(name.endswith(s) for s in VOLUME_SUFFIXES)


def _fail(exc: Exception, what: str = "") -> click.ClickException:
    msg = str(exc) if not what else f"{what}: {exc}"
    return click.ClickException(msg)


def _check_output(path: Path, force: bool, param: str = "--out") -> None:
    if path.exists() and not force:
        raise click.ClickException(f"{path} already exists; pass --force to overwrite it (or choose another {param})")
    if path.exists() and path.is_dir() != (not _is_volume_path(path)):
        kind = "a folder" if path.is_dir() else "a file"
        raise click.ClickException(f"{path} exists and is {kind}; remove it or choose another {param}")


def _nearest_existing(path: Path) -> Path:
    """``path`` or its closest ancestor that exists."""
    path = Path(os.path.abspath(path))
    while not os.path.lexists(path) and path.parent != path:
        path = path.parent
    return path


def _check_writable(path: Path, param: str = "--out", into: bool = False) -> None:
    """Fail now, before any work, if ``path`` cannot be written: its folder (``into``: the folder
    ``path`` itself, written into) must exist or be creatable, be a folder, and accept new files.
    Tested by creating and removing an empty folder there (permission bits say nothing to root,
    nor on read-only or virtual file systems such as /proc)."""
    import tempfile

    where = Path(path) if into else Path(os.path.abspath(path)).parent
    base = _nearest_existing(where)
    if not base.is_dir():
        raise click.ClickException(f"cannot write {param} {path}: {base} is a file, not a folder; "
                                   f"choose another {param}")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".clgs-write-test-", dir=base))
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise click.ClickException(f"cannot write {param} {path}: files cannot be created in {base} ({reason}); "
                                   f"choose another {param}") from None


def _new_folders(folder: Path) -> list:
    """The folders, innermost first, that writing into ``folder`` would create (none if it exists)."""
    folder = Path(os.path.abspath(folder))
    made = []
    while not os.path.lexists(folder) and folder.parent != folder:
        made.append(folder)
        folder = folder.parent
    return made


def _remove_empty(folders) -> None:
    """Remove those of ``folders`` (innermost first) this command created and left empty; a folder
    holding anything (a checkpoint, a log, another program's files) is kept, and so are its parents."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def _scan_root(scan: Path):
    """The folder of the input scan (``scan`` may name its scan.json / meta_data.json), resolved."""
    scan = Path(scan)
    if scan.is_file() and scan.name in ("scan.json", "meta_data.json"):
        scan = scan.parent
    return scan.resolve() if scan.is_dir() else None


def _scan_files(root: Path) -> list:
    """Every file and folder the scan in ``root`` is made of (resolved). A scan description that
    cannot be read protects everything in the folder."""
    import json

    found = []
    try:
        if (root / "scan.json").is_file():
            found += [root / "scan.json", root / "projections.npy", root / "truth.npy", root / "truth.nii.gz",
                      root / "truth_surface.stl"]
            doc = json.loads((root / "scan.json").read_text(encoding="utf-8"))
            found += [root / v for v in (doc.get("files") or {}).values() if isinstance(v, str)]
        if (root / "meta_data.json").is_file():
            found.append(root / "meta_data.json")
            doc = json.loads((root / "meta_data.json").read_text(encoding="utf-8"))
            found += [root / doc[k] for k in ("vol", "ct") if isinstance(doc.get(k), str)]
            for split in ("proj_train", "proj_test"):
                found += [root / str(e["file_path"]) for e in doc.get(split) or [] if isinstance(e, dict)
                          and "file_path" in e]
                found.append(root / split)
        if not found:
            found = list(root.iterdir())
    except (OSError, ValueError, TypeError, AttributeError):
        found = list(root.iterdir())
    return [f.resolve() for f in found]


def _check_not_input(path: Path, inputs, param: str = "--out") -> None:
    """Refuse an output that is, contains, or would overwrite an input: ``inputs`` are
    (label, path, is_scan) -- a scan folder is protected as a whole and file by file."""
    target = Path(path).resolve()
    for label, given, is_scan in inputs:
        if given is None:
            continue
        if is_scan:
            root = _scan_root(given)
            if root is None:
                continue
            if target == root:
                raise click.ClickException(f"{param} {path} is the input scan folder {given}; writing there would "
                                           f"replace the scan. Choose another {param}")
            if target in root.parents:
                raise click.ClickException(f"{param} {path} contains the input scan {given}; writing there would "
                                           f"delete the scan. Choose another {param}")
            for f in _scan_files(root):
                if f == target or target in f.parents:
                    raise click.ClickException(f"{param} {path} would overwrite {f.name} of the input scan {given}. "
                                               f"Choose another {param}")
        else:
            src = Path(given).resolve()
            if target == src or target in src.parents:
                what = "is" if target == src else "contains"
                raise click.ClickException(f"{param} {path} {what} the input {label} {given}; writing there would "
                                           f"destroy it. Choose another {param}")


def _out_of_memory(what: str, shape=None) -> click.ClickException:
    if shape is None:
        return click.ClickException(f"not enough memory {what}")
    n = math.prod(int(s) for s in shape)
    return click.ClickException(
        f"not enough memory {what}: the volume is {'x'.join(str(int(s)) for s in shape)} voxels "
        f"({n * 4 / 2 ** 30:.1f} GiB per float32 copy, and a method needs several); use a coarser grid "
        "(fewer voxels in the geometry's nVoxel) or a machine with more memory")


def _is_out_of_memory(exc: BaseException) -> bool:
    """MemoryError, or torch's allocation failure (a RuntimeError)."""
    return isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and "can't allocate memory" in str(exc))


def _load_volume(path: Path, spacing=None, label="volume"):
    from clgs.io.volume import VolumeError, load_volume

    if not _is_volume_path(path):
        raise click.BadParameter(f"{path}: a {label} must be .npy, .nii or .nii.gz", param_hint=label.upper())
    try:
        loaded = load_volume(path)
    except VolumeError as exc:
        raise _fail(exc) from None
    vol, sp, org = loaded
    if spacing is not None:
        sp = tuple(float(s) for s in spacing)
    return vol, sp, org


def _spacing(value):
    if value is None:
        return None
    parts = [p for p in value.replace(",", " ").split() if p]
    try:
        nums = [float(p) for p in parts]
    except ValueError:
        raise click.BadParameter(f"{value!r}: give one number or three (dZ,dY,dX) in mm", param_hint="--spacing")
    if len(nums) == 1:
        nums *= 3
    if len(nums) != 3 or min(nums) <= 0 or not all(math.isfinite(n) for n in nums):
        raise click.BadParameter(f"{value!r}: give one positive number or three (dZ,dY,dX) in mm",
                                 param_hint="--spacing")
    return tuple(nums)


def _fmt(value) -> str:
    return "inf" if isinstance(value, float) and math.isinf(value) else f"{value:.4f}"


# ====================================================================================== simulate
def _scanner_geometry(shape, spacing, views, arc_deg, mode, DSD, DSO, detector, pixel):
    """A scanner centred on the volume whose square detector sees all of it (5 % margin)."""
    import numpy as np

    from clgs.geometry import Geometry, GeometryError, shadow_half_extents

    base = Geometry.default(n_views=views, arc=math.radians(arc_deg), mode=mode, n_voxel=max(shape),
                            n_detector=detector, volume_mm=float(max(np.multiply(shape, spacing))))
    DSO = base.DSO if DSO is None else DSO
    DSD = base.DSD if DSD is None else DSD
    try:
        half_u, half_v = shadow_half_extents(np.multiply(shape, spacing), DSO, DSD, mode)
    except GeometryError as exc:
        raise click.UsageError(f"{exc} (--DSO)") from None
    if pixel is None:
        pixel = 2.0 * max(half_u, half_v) * 1.05 / detector
    d = base.to_dict()
    d.update(DSD=DSD, DSO=DSO, nVoxel=list(shape), dVoxel=list(spacing), dDetector=[pixel, pixel],
             nDetector=[detector, detector])
    return Geometry.from_dict(d)


@click.command()
@click.argument("volume", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", "-o", "out", type=click.Path(path_type=Path), required=True, help="scan folder to write")
@click.option("--views", type=click.IntRange(min=1), default=50, show_default=True, help="number of projections")
@click.option("--arc", type=FiniteFloat(min=0, min_open=True, max=360), default=180.0, show_default=True,
              help="angular range in degrees, views evenly spaced, last one short of the end")
@click.option("--mode", type=click.Choice(["cone", "parallel"]), default="cone", show_default=True)
@click.option("--DSD", "DSD", type=FiniteFloat(min=0, min_open=True), default=None,
              help="source-detector distance, mm [default: 1500]")
@click.option("--DSO", "DSO", type=FiniteFloat(min=0, min_open=True), default=None,
              help="source-rotation axis distance, mm [default: 1000]")
@click.option("--detector", type=click.IntRange(min=1), default=256, show_default=True,
              help="detector pixels per side (square detector)")
@click.option("--pixel", type=FiniteFloat(min=0, min_open=True), default=None,
              help="detector pixel size, mm [default: the detector just sees the whole volume]")
@click.option("--spacing", default=None, help="voxel size in mm, 'd' or 'dZ,dY,dX' (needed for .npy; overrides NIfTI)")
@click.option("--I0", "I0", type=FiniteFloat(min=1, min_open=True, hint="photons per pixel of an unattenuated ray; "
                                                 "counts are floored at 1, so at I0 <= 1 every projection is 0"),
              default=1e5, show_default=True,
              help="photons per pixel of the flat field (Poisson noise); more than 1")
@click.option("--sigma", type=FiniteFloat(min=0), default=10.0, show_default=True,
              help="electronic (Gaussian) noise, in photon counts")
@click.option("--scatter", type=FiniteFloat(min=0), default=0.0, show_default=True,
              help="scatter as a fraction of the primary signal")
@click.option("--seed", type=Seed(), default=0, show_default=True, help="noise seed, 0 to 2**64 - 1")
@click.option("--no-noise", is_flag=True, help="noiseless line integrals")
@click.option("--surface-level", type=FiniteFloat(), default=None,
              help="also store the truth's iso-surface at this value as truth_surface.stl")
@click.option("--force", is_flag=True, help="overwrite an existing --out")
def simulate(volume, out, views, arc, mode, DSD, DSO, detector, pixel, spacing, I0, sigma, scatter, seed,
             no_noise, surface_level, force):
    """Simulate a sparse-view X-ray scan of VOLUME (.npy/.nii/.nii.gz; attenuation in 1/mm).

    The volume is centred on the rotation axis; the scan folder stores the projections, the
    geometry, the acquisition settings and the volume itself as ground truth.
    \f

    (One function: the options' checks, the scanner, the projection and the writing share the
    parsed values; the heavier parts are helpers.)
    """
    import numpy as np

    from clgs.geometry import GeometryError
    from clgs.io.scan import Scan, ScanError

    _check_not_input(out, [("volume", volume, False)])
    _check_output(out, force)
    _check_writable(out)
    sp_override = _spacing(spacing)
    vol, sp, org = _load_volume(volume, sp_override)
    if sp is None:
        raise click.UsageError(f"{volume} is a .npy array without voxel size; give --spacing (mm)")
    if not np.all(np.isfinite(vol)):
        raise click.ClickException(f"{volume}: the volume contains NaN or Inf")
    if float(vol.min()) < 0:
        raise click.ClickException(
            f"{volume}: negative values (min {float(vol.min()):.4g}); simulate expects attenuation (1/mm, >= 0), "
            "not Hounsfield units: convert with mu = mu_water * (1 + HU / 1000), mu_water ~ 0.02/mm")
    try:
        geo = _scanner_geometry(vol.shape, sp, views, arc, mode, DSD, DSO, detector, pixel)
    except GeometryError as exc:
        raise _fail(exc, "invalid scanner") from None
    try:
        from clgs.ops.ct_projector import CTProjector
    except ImportError as exc:  # pragma: no cover - the CT module ships with clgs
        raise click.ClickException(f"the CT projector is unavailable ({exc})") from None

    click.echo(f"projecting {views} {mode}-beam views of a {'x'.join(map(str, vol.shape))} volume "
               f"onto {detector}x{detector} pixels of {geo.dDetector[0]:.3g} mm ...", err=True)
    t0 = time.perf_counter()
    projector = CTProjector(geo)
    volume32 = np.ascontiguousarray(vol, np.float32)
    step = max(1, -(-views // 20))
    chunks = [list(range(s, min(s + step, views))) for s in range(0, views, step)]
    from tqdm.auto import tqdm

    try:
        with tqdm(total=views, desc="simulate", unit="view", leave=False, disable=None) as bar:
            parts = []
            for chunk in chunks:
                parts.append(np.asarray(projector.forward(volume32, views=chunk), np.float32))
                bar.update(len(chunk))
        proj = np.concatenate(parts, axis=0)
    except MemoryError:
        raise _out_of_memory(f"to project {views} views of {detector}x{detector} pixels", vol.shape) from None
    acquisition = {"noise": not no_noise, "I0": I0, "sigma": sigma, "scatter": scatter, "seed": seed}
    if not no_noise:
        from clgs.ct.noise import add_noise

        max_p = float(proj.max()) if float(proj.max()) > 0 else 1.0  # add_noise's normalisation
        proj = np.asarray(add_noise(proj, I0=I0, sigma=sigma, scatter=scatter, seed=seed), np.float32)
        # a pixel whose count fell to the floor of 1 photon reads log(I0) * max_p: saturated
        saturated = int((proj >= np.float32(math.log(I0) * max_p) * np.float32(1 - 1e-5)).sum())
        acquisition["saturated"] = saturated
        if saturated > 0.01 * proj.size:
            click.echo(f"warning: {100.0 * saturated / proj.size:.1f} % of the detector pixels fell to the floor of "
                       f"1 photon count (at --I0 {I0:g} with --sigma {sigma:g}): their line integrals saturate and "
                       "carry no information; raise --I0", err=True)
        neg = proj < 0
        acquisition["clamped_negative"] = int(neg.sum())
        proj[neg] = 0.0  # photon counts above the flat field: clamp as R2-Gaussian's generator does
    elapsed = time.perf_counter() - t0
    meta = {
        "acquisition": acquisition,
        "provenance": {"command": "clgs simulate", "argv": sys.argv[1:], "volume": str(volume),
                       "volume_origin_xyz": None if org is None else list(org),
                       "clgs_version": __import__("clgs").__version__,
                       "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())},
    }
    surface = None
    if surface_level is not None:
        meta["truth_surface_level"] = surface_level
        from clgs.mesh.surface import SurfaceError, surface_from_volume

        try:
            surface = surface_from_volume(vol, surface_level, geometry=geo)
        except SurfaceError as exc:
            raise _fail(exc, "--surface-level") from None
    try:
        Scan(geo, proj, vol, meta, surface).save(out, overwrite=force)
    except (ScanError, FileExistsError) as exc:
        raise _fail(exc) from None
    click.echo(f"wrote {out}: {views} views, {elapsed:.1f} s")


def _load_scan(path: Path, split: str = "train"):
    """Scan.load with its errors as click errors and its repairs (ScanWarning) as messages."""
    import warnings

    from clgs.io.scan import Scan, ScanError, ScanWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ScanWarning)
        try:
            sc = Scan.load(path, split=split)
        except ScanError as exc:
            raise _fail(exc) from None
    for w in caught:
        if issubclass(w.category, ScanWarning):
            click.echo(f"warning: {w.message}", err=True)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return sc


# ====================================================================================== reconstruct
class _ReconstructCommand(click.Command):
    """Method options are parsed in a second stage, by the chosen method's own options."""

    def format_epilog(self, ctx, formatter):
        from clgs import methods

        with formatter.section("Methods"):
            formatter.write_dl(sorted(methods.describe().items()))
        formatter.write_paragraph()
        formatter.write_text("Method options (after SCAN): see 'clgs reconstruct --method NAME --help'.")


def _method_command(method) -> click.Command:
    return click.Command(f"reconstruct --method {method.name}", params=method_params(method),
                         help=method.help, add_help_option=False)


def _show_method_help(ctx, method, mcmd) -> None:
    """``clgs reconstruct --method NAME --help``: the command's help, then the method's options."""
    click.echo(ctx.get_help())
    mctx = click.Context(mcmd, info_name=mcmd.name, parent=ctx)
    formatter = mctx.make_formatter()
    formatter.write_paragraph()
    with formatter.section(f"Options of --method {method.name}"):
        formatter.write_dl([p.get_help_record(mctx) for p in mcmd.params if p.get_help_record(mctx)] or
                           [("(none)", "")])
    click.echo(formatter.getvalue().rstrip())
    ctx.exit(0)


def _method_options(ctx, method, mcmd) -> tuple:
    """(options given, keyword arguments of the run) from the words after SCAN, checked."""
    try:
        mctx = mcmd.make_context(mcmd.name, list(ctx.args), parent=ctx)
    except click.BadParameter as exc:  # a known option with a bad value: the message says it all
        raise click.UsageError(exc.format_message(), ctx) from None
    except click.UsageError as exc:
        known = ", ".join(o for p in mcmd.params for o in p.opts) or "none"
        raise click.UsageError(f"{exc.format_message()} (options of --method {method.name}: {known}; "
                               "they go after SCAN)", ctx) from None
    try:  # NaN / inf floats and impossible seeds are refused now, whatever type the method's options declared
        check_option_values(mcmd.params, mctx.params, mctx)
    except click.UsageError as exc:
        raise click.UsageError(exc.format_message(), ctx) from None
    options = {k: v for k, v in mctx.params.items() if v is not None}
    kwargs = dict(options)
    if options.get("resume") and "iterations" in mctx.params and "iterations" not in options:
        kwargs["iterations"] = None  # a resumed run goes on to the iterations it was started with
    return options, kwargs


def _prepare_outputs(scan, out, json_out, force, into_folder: bool, resuming: bool) -> tuple:
    """Check every output location before the run, so no result is lost at the end; returns the
    folders this command creates (removed again if the run fails before writing in them)."""
    _check_not_input(out, [("scan", scan, True)])
    if json_out is not None:
        _check_not_input(json_out, [("scan", scan, True)], "--json")
        if Path(json_out).resolve() == Path(out).resolve():
            raise click.UsageError("--json and --out name the same file; give the report another name")
    if not resuming:
        _check_output(out, force)
    if json_out is not None:
        _check_output(json_out, force, "--json")
    _check_writable(out, into=into_folder and out.is_dir())
    if json_out is not None:
        _check_writable(json_out, "--json")
    created = _new_folders(out if into_folder else Path(os.path.abspath(out)).parent)
    created_json = _new_folders(Path(os.path.abspath(json_out)).parent) if json_out is not None else []
    return created, created_json


@click.command(cls=_ReconstructCommand, add_help_option=False,
               context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
@click.argument("scan", type=click.Path(path_type=Path), required=False)
@click.option("--method", "-m", "method_name", default="fdk", show_default=True, help="reconstruction method")
@click.option("--out", "-o", "out", type=click.Path(path_type=Path), default=None,
              help="a volume file (.nii.gz, .nii, .npy) or a folder (volume.nii.gz, volume.npy, report.json, "
                   "method extras)")
@click.option("--split", type=click.Choice(["train", "test"]), default="train", show_default=True,
              help="which views of an R2-Gaussian dataset folder to use")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="also write the report (method, options, time, metrics) to this JSON file")
@click.option("--force", is_flag=True, help="overwrite an existing --out")
@click.option("--help", "-h", "show_help", is_flag=True, help="show this message (with --method: its options)")
@click.pass_context
def reconstruct(ctx, scan, method_name, out, split, json_out, force, show_help):
    """Reconstruct a volume from SCAN (a clgs scan folder or an R2-Gaussian dataset folder).

    With a ground truth in the scan, prints 3D PSNR / SSIM (as R2-Gaussian computes them) and
    the wall time.
    \f

    (Long because the run's outputs are cleaned up on any failure: the try blocks hold the steps
    between checking the outputs and writing the report; parsing and checks are helpers.)
    """
    from clgs import methods

    try:
        method = methods.get(method_name)
    except methods.MethodError as exc:
        raise click.BadParameter(str(exc), param_hint="--method") from None
    except ImportError as exc:
        raise click.ClickException(f"method {method_name!r} could not be loaded: {exc}") from None
    mcmd = _method_command(method)
    if show_help:
        _show_method_help(ctx, method, mcmd)
    if scan is None:
        raise click.UsageError("missing argument SCAN (a scan folder)")
    if out is None:
        raise click.UsageError("missing option --out (a volume file or a folder)")
    options, kwargs = _method_options(ctx, method, mcmd)
    into_folder = not _is_volume_path(out) and not method.atomic_dir
    resuming = bool(options.get("resume")) and into_folder and out.is_dir()
    created, created_json = _prepare_outputs(scan, out, json_out, force, into_folder, resuming)

    import numpy as np

    from clgs.io import atomic
    from clgs.io.volume import save_volume

    def files_report(files) -> dict:
        """A method's ``files``: a dict name -> path, or a list of paths (keyed by file name)."""
        if isinstance(files, dict):
            return {str(k): str(v) for k, v in files.items()}
        if isinstance(files, (str, os.PathLike)):
            files = [files]
        out_files = {}
        for f in files:
            name = Path(f).name if isinstance(f, (str, os.PathLike)) else str(f)
            out_files[name if name not in out_files else str(f)] = str(f)
        return out_files

    def finish(result, t0, folder):
        if not isinstance(result, dict) or "volume" not in result:
            raise click.ClickException(f"method {method.name} returned no volume")
        vol = np.asarray(result["volume"], np.float32)
        report["seconds"] = time.perf_counter() - t0
        if vol.shape != tuple(sc.geometry.nVoxel):
            raise click.ClickException(f"method {method.name} returned a volume of shape {vol.shape}, "
                                       f"expected {sc.geometry.nVoxel}")
        if not np.all(np.isfinite(vol)):
            raise click.ClickException(f"method {method.name} produced NaN or Inf voxels")
        if result.get("info"):
            report["info"] = result["info"]
        if result.get("files"):
            try:
                report["files"] = files_report(result["files"])
            except TypeError:
                report["files"] = str(result["files"])
        if sc.truth is not None:
            from clgs import metrics

            s, axes = metrics.ssim3d(vol, sc.truth, return_axes=True)
            report["metrics"] = {"psnr3d": metrics.psnr3d(vol, sc.truth), "ssim3d": s, "ssim3d_axes": axes}
        if folder is None:
            save_volume(out, vol, sc.geometry)
        else:
            save_volume(folder / "volume.nii.gz", vol, sc.geometry)
            atomic.save_npy(folder / "volume.npy", vol)
            atomic.write_json(folder / "report.json", report)

    sc = None
    report = {"method": method.name, "options": options, "scan": str(scan)}
    try:
        try:
            sc = _load_scan(scan, split)
            report["n_views"] = sc.n_views
            click.echo(f"{method.name}: {sc.n_views} views, {'x'.join(map(str, sc.geometry.nVoxel))} voxels",
                       err=True)
            try:
                run = method.callable()
            except (ImportError, AttributeError) as exc:
                raise click.ClickException(f"method {method.name!r} could not be loaded: {exc}") from None
            if _is_volume_path(out):
                t0 = time.perf_counter()
                finish(run(sc, None, **kwargs), t0, None)
            elif method.atomic_dir:
                with atomic.atomic_dir(out, overwrite=force) as tmp:
                    t0 = time.perf_counter()
                    finish(run(sc, tmp, **kwargs), t0, tmp)
            else:
                out.mkdir(parents=True, exist_ok=True)
                t0 = time.perf_counter()
                finish(run(sc, out, **kwargs), t0, out)
        except (MemoryError, RuntimeError) as exc:
            if not _is_out_of_memory(exc):
                raise
            if sc is None:
                raise _out_of_memory(f"to load the scan {scan}") from None
            raise _out_of_memory(f"for {method.name}", sc.geometry.nVoxel) from None
        except (ValueError, OSError, FloatingPointError) as exc:
            raise _fail(exc, f"{method.name} failed") from None
    except BaseException:  # errors and Ctrl-C alike: no empty output folder stays behind
        _remove_empty(created)
        _remove_empty(created_json)
        raise
    if json_out is not None:
        try:
            atomic.write_json(json_out, report)
        except OSError as exc:
            raise click.ClickException(f"wrote {out}, but the report could not be written to --json {json_out}: "
                                       f"{exc}") from None
    line = f"{method.name}: {report['seconds']:.2f} s"
    if "metrics" in report:
        m = report["metrics"]
        line += f", PSNR {_fmt(m['psnr3d'])} dB, SSIM {m['ssim3d']:.4f}"
    click.echo(line)
    click.echo(f"wrote {out}")


# ====================================================================================== evaluate
def _truth_from(path: Path, spacing):
    """A truth volume from a volume file or from a scan folder's truth."""
    if path.is_dir():
        from clgs.io.volume import grid_spacing_origin

        sc = _load_scan(path)
        if sc.truth is None:
            raise click.BadParameter(f"{path}: this scan has no ground truth", param_hint="--truth")
        sp, org = grid_spacing_origin(sc.geometry)
        return sc.truth, sp, org, (sc.surface, sc.meta.get("truth_surface_level"))
    vol, sp, org = _load_volume(path, spacing, "truth")
    return vol, sp, org, (None, None)


@click.command()
@click.argument("volume", type=click.Path(path_type=Path))
@click.option("--truth", "-t", type=click.Path(path_type=Path), required=True,
              help="the true volume (.npy/.nii/.nii.gz) or a scan folder holding it")
@click.option("--mask", "mask_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="a label volume; metrics are also computed over its non-zero voxels")
@click.option("--mask-level", type=FiniteFloat(), default=None,
              help="mask = truth above this value (e.g. a bone threshold, 1/mm)")
@click.option("--dilate", type=click.IntRange(min=0), default=0, show_default=True,
              help="grow the mask by this many voxels")
@click.option("--level", type=FiniteFloat(), default=None,
              help="iso-level for the surface distance (mm) between VOLUME's and the truth's surfaces")
@click.option("--surface", "surface_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="true surface mesh (STL/PLY/OBJ/npz) to compare with instead of the truth's iso-surface")
@click.option("--spacing", default=None, help="voxel size in mm for .npy inputs, 'd' or 'dZ,dY,dX'")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="write the figures to this JSON file (an infinite PSNR is written as null)")
@click.option("--force", is_flag=True, help="overwrite an existing --json")
def evaluate(volume, truth, mask_path, mask_level, dilate, level, surface_path, spacing, json_out, force):
    """Compare VOLUME with the truth: 3D PSNR / SSIM (as R2-Gaussian), masked variants, and the
    surface distance in mm when --level is given. VOLUME may also be a reconstruct output folder.

    \f
    (One function: the truth, the mask, the metrics and the optional surface distance use the
    same loaded arrays.)
    """
    import numpy as np

    from clgs import metrics
    from clgs.io import atomic

    if json_out is not None:
        _check_not_input(json_out, [("volume", volume, False), ("truth", truth, truth.is_dir()),
                                    ("mask", mask_path, False), ("surface", surface_path, False)], "--json")
        _check_output(json_out, force, "--json")
        _check_writable(json_out, "--json")
    if mask_path is not None and mask_level is not None:
        raise click.UsageError("give either --mask or --mask-level, not both")
    if volume.is_dir():
        if not (volume / "volume.nii.gz").is_file():
            raise click.BadParameter(f"{volume}: a folder without volume.nii.gz", param_hint="VOLUME")
        volume = volume / "volume.nii.gz"
    sp = _spacing(spacing)
    pred, psp, porg = _load_volume(volume, sp)
    tvol, tsp, torg, tsurf = _truth_from(truth, sp)
    if pred.shape != tvol.shape:
        raise click.UsageError(f"VOLUME {pred.shape} and --truth {tvol.shape} have different shapes (Z, Y, X)")
    if psp is not None and tsp is not None and not np.allclose(psp, tsp, rtol=1e-4):
        click.echo(f"warning: voxel sizes differ (volume {psp}, truth {tsp} mm); using the truth's", err=True)
    mask = None
    if mask_path is not None:
        mvol, _, _ = _load_volume(mask_path, sp, "mask")
        if mvol.shape != tvol.shape:
            raise click.UsageError(f"--mask {mvol.shape} does not match the volumes' shape {tvol.shape}")
        mask = mvol != 0
    elif mask_level is not None:
        mask = tvol > mask_level
    if mask is not None:
        if dilate:
            from scipy.ndimage import binary_dilation

            mask = binary_dilation(mask, iterations=dilate)
        if not mask.any():
            raise click.UsageError("the mask is empty (no voxel inside); check --mask / --mask-level")
    try:
        res = metrics.evaluate_volume(pred, tvol, mask)
    except metrics.MetricError as exc:
        raise _fail(exc) from None
    res.update(volume=str(volume), truth=str(truth))
    if mask is not None:
        res["mask_voxels"] = int(mask.sum())
    if level is not None or surface_path is not None:
        from clgs.io.mesh import MeshError, load_mesh
        from clgs.mesh.surface import SurfaceError, surface_distance, surface_from_volume

        if level is None:
            raise click.UsageError("--surface needs --level (the iso-level of VOLUME's surface)")
        sp_mm = tsp if tsp is not None else (psp if psp is not None else None)
        if sp_mm is None:
            raise click.UsageError("surface distances need voxel sizes: give --spacing for .npy volumes")
        org = torg if torg is not None else porg
        try:
            ours = surface_from_volume(pred, level, spacing=sp_mm, origin=org)
            if surface_path is not None:
                ref = load_mesh(surface_path)
            elif tsurf[0] is not None and tsurf[1] == level:
                ref = tsurf[0]  # the scan's stored true surface, made at this level
            else:
                ref = surface_from_volume(tvol, level, spacing=sp_mm, origin=org)
            res["surface"] = surface_distance(ours, ref)
        except (SurfaceError, MeshError) as exc:
            raise _fail(exc, "surface distance") from None
        res["surface"]["level"] = level
    click.echo(f"PSNR {_fmt(res['psnr3d'])} dB   SSIM {res['ssim3d']:.4f}   "
               f"(SSIM z/y/x {' '.join(f'{a:.4f}' for a in res['ssim3d_axes'])})")
    if mask is not None:
        click.echo(f"masked ({res['mask_voxels']} voxels): PSNR {_fmt(res['psnr3d_masked'])} dB   "
                   f"SSIM {res['ssim3d_masked']:.4f}")
    if "surface" in res:
        s = res["surface"]
        click.echo(f"surface distance (mm): mean {s['mean']:.3f}   p95 {s['p95']:.3f}   Hausdorff {s['hausdorff']:.3f}")
    if json_out is not None:
        atomic.write_json(json_out, res, overwrite=True)
        click.echo(f"wrote {json_out}")
