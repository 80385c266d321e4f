"""``clgs convert``: a volume from one format to another, position kept; DICOM series out in HU,
as a series of the study of the scan the volume came from."""
from __future__ import annotations

import json
from pathlib import Path

import click

from clgs.cli.common import (
    check_not_input,
    check_output,
    check_writable,
    click_error,
    is_volume_path,
    load_scan,
    load_volume_file,
    parse_spacing,
)
from clgs.cli.options import FiniteFloat, force_option, out_option
from clgs.cli.verbosity import info

#: series numbers within a scan's study: its truth and each method's reconstruction apart
SERIES_NUMBERS = {"truth": 100, "fdk": 101, "sart": 102, "r2gs": 103, "shape": 104}


def _series_number(method: str | None) -> int:
    import zlib

    if method is None:
        return 1
    return SERIES_NUMBERS.get(method, 200 + zlib.crc32(method.encode()) % 800)


def _read_report(path: Path) -> dict:
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise click.ClickException(f"{path}: not a readable run report ({exc})") from None
    if not isinstance(doc, dict):
        raise click.ClickException(f"{path}: not a run report (a JSON object with 'method' and 'scan')")
    return doc


def _scan_folder_of_report(report: dict, where: Path):
    """The scan folder a run report names (absolute, or relative to the working folder or the
    report's), or None when it is not there."""
    from clgs.io.scan import is_scan_folder

    names = [report.get("scan_path"), report.get("scan")]
    for name in (n for n in names if isinstance(n, str) and n):
        for cand in (Path(name), where / name):
            folder = cand.parent if cand.name in ("scan.json", "meta_data.json") else cand
            if is_scan_folder(folder) or (folder / "meta_data.json").is_file():
                return folder
    return None


def _identity_and_series(volume: Path, scan_dir, report_path):
    """(identity or None, method or None, report or None): where VOLUME's series belongs."""
    from clgs.io.dicom_identity import scan_identity
    from clgs.io.scan import is_scan_folder

    report, method = None, None
    if report_path is None and (volume.parent / "report.json").is_file() and volume.is_file():
        report_path = volume.parent / "report.json"
    if report_path is not None:
        report = _read_report(report_path)
        method = report.get("method") if isinstance(report.get("method"), str) else None
    if scan_dir is None and volume.is_file() and is_scan_folder(volume.parent) \
            and volume.name.lower().startswith("truth."):
        scan_dir, method = volume.parent, "truth"  # a scan's own truth: a series of the scan's study
    if scan_dir is not None:
        return scan_identity(load_scan(scan_dir, (report or {}).get("split", "train"))), method, report
    if report is None:
        return None, None, None
    if isinstance(report.get("scan_identity"), dict) and report["scan_identity"].get("StudyInstanceUID"):
        return {k: str(v) for k, v in report["scan_identity"].items()}, method, report
    folder = _scan_folder_of_report(report, Path(report_path).parent)
    if folder is None:
        click.echo(f"warning: {report_path} names the scan {report.get('scan')!r}, which is not there: the series "
                   "gets a study of its own; give --scan SCAN to put it in the scan's study", err=True)
        return None, method, report
    return scan_identity(load_scan(folder, report.get("split", "train"))), method, report


def _description(method, report, volume: Path) -> tuple:
    """(series description, derivation) of VOLUME."""
    if method == "truth":
        return "clgs simulated scan: truth", "the attenuation volume the scan was simulated from"
    if method is None:
        return f"clgs: {volume.name}"[:64], ""
    n = (report or {}).get("n_views")
    views = f", {n} views" if isinstance(n, int) else ""
    options = (report or {}).get("options") or {}
    shown = ", ".join(f"{k}={v}" for k, v in sorted(options.items()) if not isinstance(v, (dict, list)))
    derivation = f"reconstructed by clgs {method}{views}" + (f" ({shown})" if shown else "")
    return f"clgs {method.upper()}{views}"[:64], derivation


@click.command()
@click.argument("volume", type=click.Path(path_type=Path))
@click.argument("out_arg", metavar="", type=click.Path(path_type=Path), required=False)
@out_option("the volume file to write (.nii.gz, .mha, .nrrd, .npy), or with --dicom the series folder",
            type=click.Path(path_type=Path))
@click.option("--dicom", is_flag=True, help="write --out as a folder holding a DICOM CT series (Hounsfield units)")
@click.option("--hu", is_flag=True, help="VOLUME holds Hounsfield units (a CT): convert them to attenuation first")
@click.option("--to-hu", is_flag=True, help="write Hounsfield units at --kev instead of attenuation (the unit is "
                                            "recorded in the header of --out; DICOM always holds HU)")
@click.option("--kev", type=FiniteFloat(min=40, max=150), default=70.0, show_default=True,
              help="X-ray energy of the HU <-> attenuation conversion (water's attenuation from NIST XCOM)")
@click.option("--scan", "scan_dir", type=click.Path(exists=True, path_type=Path), default=None,
              help="DICOM: the scan VOLUME was reconstructed from; the series joins its study and frame of "
                   "reference (and its patient, for a scan simulated from a DICOM CT) [default: the scan named "
                   "by the run's report.json beside VOLUME]")
@click.option("--report", "report_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="DICOM: the run's report (reconstruct --json FILE) when it does not lie beside VOLUME")
@click.option("--series-number", type=click.IntRange(min=0, max=2 ** 31 - 1), default=None,
              help="DICOM: the series number [default: by method: truth 100, fdk 101, sart 102, r2gs 103, "
                   "shape 104; 1 for a volume of no run]")
@click.option("--series-description", default=None, help="DICOM: the series description (at most 64 characters) "
                                                         "[default: the method and views, or the file name]")
@click.option("--axes", type=click.Choice(["zyx", "xyz"]), default="zyx", show_default=True,
              help="axis order of a .npy volume")
@click.option("--spacing", default=None, help="voxel size in mm for a .npy volume, 'd' or 'dZ,dY,dX'")
@force_option("replace an existing --out")
def convert(volume, out_arg, out, dicom, hu, to_hu, kev, scan_dir, report_path, series_number, series_description, axes,
            spacing, force):
    """Convert VOLUME (.npy, NIfTI, MetaImage, NRRD, a DICOM series) to --out (.nii.gz, .mha,
    .nrrd, .npy, or with --dicom a DICOM series folder), keeping its spacing and position.

    clgs works in attenuation (1/mm); --hu reads Hounsfield units, --to-hu writes them (the unit
    is written into the header of --out: NIfTI descrip, MetaImage/NRRD ValueUnit), and a DICOM series is
    always written in HU at --kev (what CT viewers expect), rounded to 1 HU. A DICOM series
    belongs to the study of the scan VOLUME was reconstructed from (docs/dicom.md).
    """
    import numpy as np

    from clgs.io.units import hu_to_mu

    if out_arg is not None and out is not None:
        raise click.UsageError("give the output once: -o/--out OUT")
    out = out if out is not None else out_arg  # `clgs convert VOLUME OUT`, the earlier form, still reads
    if out is None:
        raise click.UsageError("missing option -o/--out (the file or, with --dicom, the folder to write)")
    if not dicom and not is_volume_path(out):
        raise click.BadParameter(f"{out}: give a volume file (.nii.gz, .mha, .nrrd, .npy) or --dicom for a "
                                 "DICOM series folder", param_hint="--out")
    if dicom and to_hu:
        info("note: a DICOM series always holds HU; --to-hu changes nothing there")
    if not dicom and (scan_dir or report_path or series_number is not None or series_description):
        raise click.UsageError("--scan, --report, --series-number and --series-description are for --dicom")
    check_not_input(out, [("volume", volume, False)], param="--out")
    if scan_dir is not None:
        check_not_input(out, [("scan", scan_dir, True)], param="--out")
    if out.exists() and not force:
        raise click.ClickException(f"{out} already exists; pass --force to replace it")
    if not dicom:
        check_output(out, force, param="--out")
    check_writable(out, param="--out")
    loaded = load_volume_file(volume, parse_spacing(spacing), attenuation=not hu, axes=axes)
    vol, sp, org = loaded
    if sp is None:
        raise click.UsageError(f"{volume} is a .npy array without voxel size; give --spacing (mm)")
    if not np.all(np.isfinite(vol)):
        raise click.ClickException(f"{volume}: the volume contains NaN or Inf")
    if org is None:  # a bare array: centred on the origin, as everywhere in clgs
        org = tuple(-0.5 * (np.asarray(vol.shape[::-1], float) - 1) * np.asarray(sp[::-1], float))
    mu = hu_to_mu(vol, kev) if hu else vol
    from clgs.io.outputs import OutputBusy, lock

    try:
        with lock(out, "--out"):  # one writer at a time (docs/output-rule.md)
            _convert_into(volume, out, dicom, mu, sp, org, kev, to_hu, loaded, scan_dir, report_path,
                          series_number, series_description, force)
    except OutputBusy as exc:
        raise click.ClickException(str(exc)) from None


def _convert_into(volume, out, dicom, mu, sp, org, kev, to_hu, loaded, scan_dir, report_path, series_number,
                  series_description, force) -> None:
    import numpy as np

    from clgs.io.units import HU, MU, header_text, mu_to_hu
    from clgs.io.volume import VolumeError, save_volume

    try:
        if dicom:
            _write_dicom(volume, out, mu, sp, org, kev, scan_dir, report_path, series_number, series_description,
                         force)
            return
        data = np.asarray(mu_to_hu(mu, kev), np.float32) if to_hu else mu
        units = HU if to_hu else MU
        save_volume(out, data, spacing=sp, origin=org, overwrite=force,
                    orientation=getattr(loaded, "orientation", None), units=units, kev=kev if to_hu else None)
    except (VolumeError, ValueError) as exc:
        raise click_error(exc) from None
    click.echo(f"wrote {out} ({header_text(units, kev if to_hu else None)[0].removeprefix('clgs: ')})")
    if to_hu and out.name.lower().endswith(".npy"):
        click.echo(f"warning: {out.name} is a bare array: nothing records that it holds HU at {kev:g} keV; "
                   "prefer .nii.gz, .mha or .nrrd", err=True)


def _write_dicom(volume, out, mu, sp, org, kev, scan_dir, report_path, series_number, series_description, force):
    from clgs.io.dicom import save_dicom_series

    identity, method, report = _identity_and_series(Path(volume), scan_dir, report_path)
    description, derivation = _description(method, report, Path(volume))
    report_out = save_dicom_series(out, mu, sp, org, kev=kev, identity=identity, overwrite=force,
                                   description=series_description or description,
                                   series_number=_series_number(method) if series_number is None else series_number,
                                   derivation=derivation)
    where = "its own study" if identity is None else f"the study {report_out['study_uid']}"
    click.echo(f"wrote {out}: {report_out['files']} DICOM slices, {report_out['hu_min']} to {report_out['hu_max']} "
               f"HU at {kev:g} keV; series {report_out['series_number']} of {where}")
    if report_out["clipped"]:
        click.echo(f"warning: {report_out['clipped']} voxels lay beyond the 16-bit HU range and were clipped",
                   err=True)
