"""``clgs simulate``: a sparse-view scan of any CT volume. Heavy modules load when it runs."""
from __future__ import annotations

import math
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
from clgs.cli.options import FiniteFloat, Seed, distance_options


def _scanner_geometry(shape, spacing, views, arc_deg, mode, DSD, DSO, detector, pixel, centre_xyz=(0, 0, 0)):
    """A scanner turning about the volume's centre (``centre_xyz``, world mm) whose square detector
    sees all of it (5 % margin)."""
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
             nDetector=[detector, detector], isocentre=[float(c) for c in np.asarray(centre_xyz, float)[::-1]])
    return Geometry.from_dict(d)


@click.command()
@click.argument("volume", type=click.Path(path_type=Path))
@click.option("--out", "-o", "out", type=click.Path(path_type=Path), required=True, help="scan folder to write")
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
              help="photons per pixel of the flat field (Poisson noise); more than 1")
@click.option("--sigma", type=FiniteFloat(min=0), default=10.0, show_default=True,
              help="electronic (Gaussian) noise, in photon counts")
@click.option("--scatter", type=FiniteFloat(min=0), default=0.0, show_default=True,
              help="scatter as a fraction of the primary signal")
@click.option("--seed", type=Seed(), default=0, show_default=True, help="noise seed, 0 to 2**64 - 1")
@click.option("--no-noise", is_flag=True, help="noiseless line integrals")
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
@click.option("--force", is_flag=True, help="overwrite an existing --out")
def simulate(volume, out, axes, hu, kev, views, arc, mode, DSD, DSO, detector, pixel, spacing, I0, sigma, scatter, seed,
             no_noise, surface_level, grid, grid_spacing, protocol, geometry_file, force):
    """Simulate a sparse-view X-ray scan of VOLUME (attenuation in 1/mm, or Hounsfield units with
    --hu): .npy, NIfTI, MetaImage (.mha/.mhd), NRRD, or a DICOM series (its folder or a .dcm file).

    The rotation axis passes through the volume's centre, and every file written keeps the
    input's world position (origin and spacing). The scan folder stores the projections, the
    geometry, the acquisition settings and the truth on the reconstruction grid (--grid).
    Projections come from a grid twice as fine as the reconstruction grid unless
    --simulation same.
    \f

    (One function: the options' checks, the scanner, the projection and the writing share the
    parsed values; the heavier parts are helpers.)
    """
    import numpy as np

    from clgs.geometry import GeometryError
    from clgs.io.scan import Scan, ScanError

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
    from clgs.ct.simulation_grid import fine_bytes, parse_grid, projection_volume, resample_box
    from clgs.errors import InputError

    if grid is not None and grid_spacing is not None:
        raise click.UsageError("give --grid (voxels) or --grid-spacing (mm), not both")
    try:
        recon_shape = parse_grid(grid)
    except InputError as exc:
        raise click.BadParameter(str(exc), param_hint="--grid") from None
    grid_sp = parse_spacing(grid_spacing, "--grid-spacing") if grid_spacing is not None else None
    vol, sp, org = load_volume_file(volume, sp_override, attenuation=not hu, axes=axes)
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
    # the world point the scanner turns about: the input's centre (0 for a bare .npy array)
    centre_xyz = np.zeros(3)
    if org is not None:
        centre_xyz = np.asarray(org, float) + 0.5 * (np.asarray(vol.shape[::-1]) - 1) * np.asarray(sp[::-1], float)
    if protocol == "fine":
        check_memory(f"the fine simulation grid for a {'x'.join(map(str, recon_shape))} reconstruction grid",
                     2.0 * fine_bytes(recon_shape, vol.shape), "use --simulation same or a coarser --grid")
    if not np.all(np.isfinite(vol)):
        raise click.ClickException(f"{volume}: the volume contains NaN or Inf")
    if hu:
        from clgs.io.units import hu_to_mu

        vol = hu_to_mu(vol, kev)
    if float(vol.min()) < 0:
        raise click.ClickException(
            f"{volume}: negative values (min {float(vol.min()):.4g}); simulate expects attenuation (1/mm, >= 0); "
            "for Hounsfield units (a CT) add --hu (and --kev for the energy)")
    try:
        if geometry_file is not None:
            from clgs.geometry import Geometry, read_geometry

            geo = read_geometry(geometry_file, {"nVoxel": list(recon_shape), "dVoxel": list(recon_sp)})
            # the volume stays where the input lay: its centre is the file's offOrigin in the scanner's frame
            iso = centre_xyz - np.asarray(geo.offOrigin[::-1], float)
            geo = Geometry.from_dict({**geo.to_dict(), "isocentre": [float(c) for c in iso[::-1]]})
            views, mode = geo.n_views, geo.mode
            check_memory(f"simulating {views} views of {geo.nDetector[0]} x {geo.nDetector[1]} pixels",
                         3.0 * 4 * views * geo.nDetector[0] * geo.nDetector[1], "use fewer views or a smaller detector")
        else:
            geo = _scanner_geometry(recon_shape, recon_sp, views, arc, mode, DSD, DSO, detector, pixel, centre_xyz)
    except GeometryError as exc:
        raise click_error(exc, "invalid scanner") from None
    _warn_if_thinner_than_a_row(volume, vol.shape, sp, geo)
    truth = resample_box(vol, recon_shape)
    source = projection_volume(vol, recon_shape, protocol)
    sim = geo.to_dict()
    sim.update(nVoxel=list(source.shape), dVoxel=[float(e) / n for e, n in zip(extent, source.shape)])
    sim_geo = type(geo).from_dict(sim)
    try:
        from clgs.ops.ct_projector import CTProjector
    except ImportError as exc:  # pragma: no cover - the CT module ships with clgs
        raise click.ClickException(f"the CT projector is unavailable ({exc})") from None

    click.echo(f"projecting {views} {mode}-beam views of a {'x'.join(map(str, source.shape))} volume "
               f"({protocol} grid; reconstruction grid {'x'.join(map(str, recon_shape))}) "
               f"onto {geo.nDetector[0]}x{geo.nDetector[1]} pixels of {geo.dDetector[0]:.3g} mm ...", err=True)
    t0 = time.perf_counter()
    projector = CTProjector(sim_geo)
    volume32 = np.ascontiguousarray(source, np.float32)
    step = max(1, -(-views // 20))
    chunks = [list(range(s, min(s + step, views))) for s in range(0, views, step)]
    from clgs.progress import progress_bar

    try:
        with progress_bar(total=views, desc="simulate", unit="view", leave=False, disable=None) as bar:
            parts = []
            for chunk in chunks:
                parts.append(np.asarray(projector.forward(volume32, views=chunk), np.float32))
                bar.update(len(chunk))
        proj = np.concatenate(parts, axis=0)
    except MemoryError:
        raise out_of_memory(f"to project {views} views of {geo.nDetector[0]}x{geo.nDetector[1]} pixels",
                            vol.shape) from None
    if not np.all(np.isfinite(proj)):
        raise click.ClickException(
            f"{volume}: its line integrals overflow 32-bit floats (attenuation up to {float(vol.max()):.3g} 1/mm "
            f"over paths of up to {float(max(np.multiply(vol.shape, sp))):.0f} mm); attenuation is in 1/mm "
            "(bone about 0.05): check the volume's units")
    acquisition = {"noise": not no_noise, "I0": I0, "sigma": sigma, "scatter": scatter, "seed": seed,
                   "simulation": {"protocol": protocol, "projected_grid": list(source.shape),
                                  "reconstruction_grid": list(recon_shape)}}
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
    if dicom_source:
        meta["dicom_source"] = dicom_source
    surface = None
    if surface_level is not None:
        meta["truth_surface_level"] = surface_level
        from clgs.mesh.surface import SurfaceError, surface_from_volume

        try:
            surface = surface_from_volume(truth, surface_level, geometry=geo)
        except SurfaceError as exc:
            raise click_error(exc, "--surface-level") from None
    try:
        Scan(geo, proj, truth, meta, surface).save(out, overwrite=force)
    except (ScanError, FileExistsError) as exc:
        raise click_error(exc) from None
    click.echo(f"wrote {out}: {views} views, {elapsed:.1f} s")


def _warn_if_thinner_than_a_row(path, shape, spacing, geo) -> None:
    """A volume less than one detector row high (at the rotation axis) projects between rows and
    mostly vanishes from the scan: say so, with the numbers and what to change."""
    import numpy as np

    height = shape[0] * float(spacing[0])
    row = float(np.max(np.linalg.norm(geo.view_vectors(scene=False)[:, 9:12], axis=1) / geo.magnification()))
    if height < row:
        click.echo(f"warning: {path} is {height:.3g} mm high, less than one detector row at the rotation axis "
                   f"({row:.3g} mm): its projection falls between rows and mostly vanishes; use a smaller --pixel, "
                   "more --detector pixels, or a thicker volume", err=True)
