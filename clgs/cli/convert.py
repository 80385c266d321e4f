"""``clgs convert``: a volume from one format to another, position kept; DICOM series out in HU."""
from __future__ import annotations

from pathlib import Path

import click

from clgs.cli.common import (
    check_not_input,
    check_output,
    check_writable,
    click_error,
    is_volume_path,
    load_volume_file,
    parse_spacing,
)
from clgs.cli.options import FiniteFloat


@click.command()
@click.argument("volume", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--dicom", is_flag=True, help="write OUT as a folder holding a DICOM CT series (Hounsfield units)")
@click.option("--hu", is_flag=True, help="VOLUME holds Hounsfield units (a CT): convert them to attenuation first")
@click.option("--to-hu", is_flag=True, help="write Hounsfield units instead of attenuation (DICOM always holds HU)")
@click.option("--kev", type=FiniteFloat(min=40, max=150), default=70.0, show_default=True,
              help="X-ray energy of the HU <-> attenuation conversion (water's attenuation from NIST XCOM)")
@click.option("--axes", type=click.Choice(["zyx", "xyz"]), default="zyx", show_default=True,
              help="axis order of a .npy volume")
@click.option("--spacing", default=None, help="voxel size in mm for a .npy volume, 'd' or 'dZ,dY,dX'")
@click.option("--force", is_flag=True, help="replace an existing OUT")
def convert(volume, out, dicom, hu, to_hu, kev, axes, spacing, force):
    """Convert VOLUME (.npy, NIfTI, MetaImage, NRRD, a DICOM series) to OUT (.nii.gz, .mha,
    .nrrd, .npy, or with --dicom a DICOM series folder), keeping its spacing and position.

    clgs works in attenuation (1/mm); --hu reads Hounsfield units, --to-hu writes them, and a
    DICOM series is always written in HU at --kev (what CT viewers expect), rounded to 1 HU.
    """
    import numpy as np

    from clgs.io.units import hu_to_mu, mu_to_hu
    from clgs.io.volume import VolumeError, save_volume

    if not dicom and not is_volume_path(out):
        raise click.BadParameter(f"{out}: give a volume file (.nii.gz, .mha, .nrrd, .npy) or --dicom for a "
                                 "DICOM series folder", param_hint="OUT")
    if dicom and to_hu:
        click.echo("note: a DICOM series always holds HU; --to-hu changes nothing there", err=True)
    check_not_input(out, [("volume", volume, False)], param="OUT")
    if out.exists() and not force:
        raise click.ClickException(f"{out} already exists; pass --force to replace it")
    if not dicom:
        check_output(out, force, param="OUT")
    check_writable(out, param="OUT")
    vol, sp, org = load_volume_file(volume, parse_spacing(spacing), attenuation=not hu, axes=axes)
    if sp is None:
        raise click.UsageError(f"{volume} is a .npy array without voxel size; give --spacing (mm)")
    if not np.all(np.isfinite(vol)):
        raise click.ClickException(f"{volume}: the volume contains NaN or Inf")
    if org is None:  # a bare array: centred on the origin, as everywhere in clgs
        org = tuple(-0.5 * (np.asarray(vol.shape[::-1], float) - 1) * np.asarray(sp[::-1], float))
    mu = hu_to_mu(vol, kev) if hu else vol
    try:
        if dicom:
            from clgs.io.dicom import save_dicom_series

            report = save_dicom_series(out, mu, sp, org, kev=kev, overwrite=force,
                                       description=f"clgs: {Path(volume).name}")
            click.echo(f"wrote {out}: {report['files']} DICOM slices, {report['hu_min']} to {report['hu_max']} HU "
                       f"at {kev:g} keV")
            if report["clipped"]:
                click.echo(f"warning: {report['clipped']} voxels lay beyond the 16-bit HU range and were clipped",
                           err=True)
            return
        data = np.asarray(mu_to_hu(mu, kev), np.float32) if to_hu else mu
        save_volume(out, data, spacing=sp, origin=org, overwrite=force)
    except (VolumeError, ValueError) as exc:
        raise click_error(exc) from None
    click.echo(f"wrote {out} ({'HU at %g keV' % kev if to_hu else 'attenuation, 1/mm'})")
