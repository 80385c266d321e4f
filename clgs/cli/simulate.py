"""``clgs simulate``: a sparse-view scan of any CT volume. Heavy modules load when it runs."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import click

from clgs.cli.common import (
    check_memory,
    check_not_input,
    check_output,
    check_writable,
    click_error,
    load_volume_file,
    out_of_memory,
    parse_spacing,
)
from clgs.cli.options import AliasOption, FiniteFloat, Seed, distance_options, force_option, out_option
from clgs.cli.settings import option_settings
from clgs.cli.verbosity import detail, info

SIMULATION_SETTINGS = ("views", "arc", "mode", "DSO", "DSD", "detector", "pixel", "I0", "sigma", "scatter", "seed",
                       "noise", "kev", "grid", "grid_spacing", "simulation", "surface_level")


@click.command()
@option_settings(*SIMULATION_SETTINGS, owner="clgs simulate")
@click.argument("volume", type=click.Path(path_type=Path))
@out_option("scan folder to write", type=click.Path(path_type=Path), required=True)
@click.option("--axes", type=click.Choice(["zyx", "xyz"]), default="zyx", show_default=True,
              help="axis order of a .npy volume: zyx (clgs) or xyz (R2-Gaussian's vol_gt.npy)")
@click.option("--hu", is_flag=True, help="the volume holds Hounsfield units (a CT, DICOM): convert them to "
                                         "attenuation, mu = mu_water (1 + HU / 1000), at --kev")
@click.option("--kev", type=FiniteFloat(min=40, max=150), default=70.0, show_default=True,
              help="X-ray energy for --hu (water's attenuation from NIST XCOM, 40-150 keV)")
@click.option("--views", type=click.IntRange(min=1), default=50, show_default=True, help="number of projections")
@click.option("--arc", type=FiniteFloat(min=0, min_open=True, max=360), default=180.0, show_default=True,
              help="angular range in degrees, views evenly spaced, last one short of the end")
@click.option("--mode", type=click.Choice(["cone", "parallel"]), default="cone", show_default=True)
@distance_options("source-rotation axis distance, mm [default: 1000]", "source-detector distance, mm [default: 1500]")
@click.option("--detector", type=click.IntRange(min=1), default=256, show_default=True,
              help="detector pixels per side (square detector)")
@click.option("--pixel", type=FiniteFloat(min=0, min_open=True), default=None,
              help="detector pixel size, mm [default: the detector just sees the whole volume]")
@click.option("--spacing", default=None, help="voxel size in mm, 'd' or 'dZ,dY,dX' (needed for .npy; overrides NIfTI)")
@click.option("--I0", "I0", type=FiniteFloat(min=1, min_open=True, hint="photons per pixel of an unattenuated ray; "
                                                 "counts are floored at 1, so at I0 <= 1 every projection is 0"),
              default=1e5, show_default=True,
              help="Poisson noise: photon count of an unattenuated ray, with TIGRE's normalisation: counts are "
                   "I0 exp(-p / max p), so the most attenuating ray keeps I0/e whatever the object (a relative "
                   "noise level, not a dose; docs/formats.md); more than 1")
@click.option("--sigma", type=FiniteFloat(min=0), default=10.0, show_default=True,
              help="electronic (Gaussian) noise, in photon counts")
@click.option("--scatter", type=FiniteFloat(min=0), default=0.0, show_default=True,
              help="scatter as a fraction of the primary signal")
@click.option("--seed", type=Seed(), default=0, show_default=True, help="noise seed, 0 to 2**64 - 1")
@click.option("--noise/--no-noise", "noise", cls=AliasOption, aliases=(" /--noiseless",), default=True,
              show_default=True, help="Poisson + electronic noise (--no-noise: noiseless line integrals)")
@click.option("--surface-level", type=FiniteFloat(), default=None,
              help="also store the truth's iso-surface at this value as truth_surface.stl")
@click.option("--grid", default=None,
              help="reconstruction grid, N or NZ,NY,NX voxels over the input's field of view; the truth is "
                   "resampled onto it [default: the input's own grid]")
@click.option("--grid-spacing", default=None,
              help="reconstruction voxel size in mm, 'd' or 'dZ,dY,dX', instead of --grid (rounded to whole voxels "
                   "over the input's field of view)")
@click.option("--simulation", "protocol", type=click.Choice(["fine", "same"]), default="fine", show_default=True,
              help="fine: project a volume at least twice as fine as the reconstruction grid (no inverse crime); "
                   "same: project the truth on the reconstruction grid (R2-Gaussian's protocol)")
@click.option("--geometry", "geometry_file", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="scanner and views from a geometry JSON (TIGRE names or per-view 'vectors', mm in the "
                   "scanner's frame; docs/formats.md) instead of --views, --arc, --mode, --DSO, --DSD, --detector "
                   "and --pixel; the volume keeps its place, centred at the file's offOrigin (default 0) in that "
                   "frame, on the reconstruction grid (--grid), which replaces the file's nVoxel and dVoxel")
@force_option("replace an existing scan folder --out")
def simulate(volume, out, axes, hu, kev, views, arc, mode, DSD, DSO, detector, pixel, spacing, I0, sigma, scatter, seed,
             noise, surface_level, grid, grid_spacing, protocol, geometry_file, force):
    """Simulate a sparse-view X-ray scan of VOLUME (attenuation in 1/mm, or Hounsfield units with
    --hu): .npy, NIfTI, MetaImage (.mha/.mhd), NRRD, or a DICOM series (its folder or a .dcm file).

    The rotation axis passes through the volume's centre, and every volume written (the truth,
    later the reconstructions) keeps the input's affine and array order (LAS, LPS, permuted).
    The scan folder stores the projections, the geometry, the acquisition settings and the
    truth on the reconstruction grid (--grid).
    Projections come from a grid twice as fine as the reconstruction grid unless
    --simulation same.
    \f

    (The options' checks and the writing; the simulation is :func:`clgs.ct.simulate.simulate_scan`.)
    """
    import numpy as np

    from clgs.geometry import GeometryError
    from clgs.io.scan import ScanError

    check_not_input(out, [("volume", volume, False)])
    check_output(out, force, kind="scan")
    check_writable(out)
    sp_override = parse_spacing(spacing)
    if geometry_file is not None:
        ctx = click.get_current_context()
        given = [f"--{p}" for p in ("views", "arc", "mode", "DSO", "DSD", "detector", "pixel")
                 if ctx.get_parameter_source(p) == click.core.ParameterSource.COMMANDLINE]
        if given:
            raise click.UsageError(f"--geometry gives the scanner and the views: leave out {', '.join(given)}")
    # projections, their noisy copy and the parts joined: three float32 copies of views x detector^2
    check_memory(f"simulating {views} views of {detector} x {detector} pixels", 3.0 * 4 * views * detector ** 2,
                 "use fewer --views or a smaller --detector")
    from clgs.ct.simulation_grid import fine_bytes, parse_grid
    from clgs.errors import InputError

    if grid is not None and grid_spacing is not None:
        raise click.UsageError("give --grid (voxels) or --grid-spacing (mm), not both")
    try:
        recon_shape = parse_grid(grid)
    except InputError as exc:
        raise click.BadParameter(str(exc), param_hint="--grid") from None
    grid_sp = parse_spacing(grid_spacing, "--grid-spacing") if grid_spacing is not None else None
    loaded = load_volume_file(volume, sp_override, attenuation=not hu, axes=axes, doubt_negatives=False)
    vol, sp, org = loaded
    from clgs.io.dicom_identity import DicomIdentityError, input_identity

    try:  # a DICOM input's patient, study and frame of reference, for the reconstructions' series
        dicom_source = input_identity(volume)
    except DicomIdentityError as exc:
        dicom_source = None
        click.echo(f"warning: {exc}; DICOM series of its reconstructions will be anonymous", err=True)
    if sp is None:
        raise click.UsageError(f"{volume} is a .npy array without voxel size; give --spacing (mm)")
    extent = np.multiply(vol.shape, sp)  # (Z, Y, X) mm: the field of view both grids cover
    if grid_sp is not None:
        recon_shape = tuple(max(1, int(round(float(e) / float(d)))) for e, d in zip(extent, grid_sp))
    recon_shape = tuple(vol.shape) if recon_shape is None else recon_shape
    recon_sp = tuple(float(e) / n for e, n in zip(extent, recon_shape))
    if protocol == "fine":
        check_memory(f"the fine simulation grid for a {'x'.join(map(str, recon_shape))} reconstruction grid",
                     2.0 * fine_bytes(recon_shape, vol.shape), "use --simulation same or a coarser --grid")
    if not np.all(np.isfinite(vol)):
        raise click.ClickException(f"{volume}: the volume contains NaN or Inf")
    if geometry_file is not None:
        from clgs.geometry import read_geometry

        try:
            peek = read_geometry(geometry_file, {"nVoxel": list(recon_shape), "dVoxel": list(recon_sp)})
        except GeometryError as exc:
            raise click_error(exc, "invalid scanner") from None
        check_memory(f"simulating {peek.n_views} views of {peek.nDetector[0]} x {peek.nDetector[1]} pixels",
                     3.0 * 4 * peek.n_views * peek.nDetector[0] * peek.nDetector[1],
                     "use fewer views or a smaller detector")
    from clgs.ct.simulate import simulate_scan

    meta = {
        "provenance": {"command": "clgs simulate", "argv": sys.argv[1:], "volume": str(volume),
                       "volume_origin_xyz": None if org is None else list(org),
                       "volume_units": "HU" if hu else "1/mm",
                       **_input_frame(loaded),
                       "clgs_version": __import__("clgs").__version__,
                       "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())},
    }
    if dicom_source:
        meta["dicom_source"] = dicom_source
    t0 = time.perf_counter()
    try:
        scan = simulate_scan(
            vol, sp, org, orientation=loaded.orientation, hu=hu, kev=kev, views=views, arc_deg=arc, mode=mode,
            DSO=DSO, DSD=DSD, detector=detector, pixel=pixel, geometry=geometry_file,
            grid=recon_shape, protocol=protocol, noise=noise,
            I0=I0, sigma=sigma, scatter=scatter, seed=seed, surface_level=surface_level, name=str(volume),
            warn=lambda message: click.echo(f"warning: {message}", err=True), meta=meta,
            announce=lambda geo, shape: info(
                f"projecting {geo.n_views} {geo.mode}-beam views of a {'x'.join(map(str, shape))} volume "
                f"({protocol} grid; reconstruction grid {'x'.join(map(str, recon_shape))}) onto "
                f"{geo.nDetector[0]}x{geo.nDetector[1]} pixels of {geo.dDetector[0]:.3g} mm ..."))
    except GeometryError as exc:
        raise click_error(exc, "invalid scanner") from None
    except MemoryError:
        raise out_of_memory(f"to project {views} views", vol.shape) from None
    except InputError as exc:
        raise click_error(exc) from None
    elapsed = time.perf_counter() - t0
    views = scan.n_views
    acq = scan.meta.get("acquisition") or {}
    detail("settings: " + ", ".join(f"{k}={acq[k]}" for k in ("noise", "I0", "sigma", "scatter", "seed") if k in acq))
    try:
        scan.save(out, overwrite=force)
    except (ScanError, FileExistsError) as exc:
        raise click_error(exc) from None
    click.echo(f"wrote {out}: {views} views, {elapsed:.1f} s")


def _input_frame(loaded) -> dict:
    """The input's frame as scan.json records it: its axis codes, and (for files that place
    themselves) its voxel-to-world matrix and its array's shape as the file indexes it (i, j, k);
    for an oblique file, those of the axis-aligned grid it was resampled onto."""
    import numpy as np
    from nibabel.orientations import axcodes2ornt

    from clgs.io.orientation import file_affine

    vol, sp, org = loaded
    frame = {"volume_orientation": loaded.orientation}
    if sp is not None and org is not None:
        aff = file_affine(sp, org, vol.shape, loaded.orientation)
        frame["volume_affine"] = [[float(v) for v in row] for row in aff]
        axes = axcodes2ornt(tuple(loaded.orientation))[:, 0].astype(int)  # world axis of each file axis
        frame["volume_shape"] = [int(np.asarray(vol.shape[::-1])[a]) for a in axes]
    return frame
