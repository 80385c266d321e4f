"""``clgs import``: raw detector images (counts) into a scan folder of line integrals."""
from __future__ import annotations

import json
from pathlib import Path

import click

from clgs.cli.options import FiniteFloat, distance_options


def _ints(value, n, what, param):
    if value is None:
        return None
    parts = [p for p in str(value).replace(",", " ").split() if p]
    try:
        nums = [int(p) for p in parts]
    except ValueError:
        raise click.BadParameter(f"{value!r}: give {n} whole numbers ({what})", param_hint=param) from None
    if len(nums) != n:
        raise click.BadParameter(f"{value!r}: give {n} whole numbers ({what})", param_hint=param)
    return nums


def _angles(path):
    """Degrees, one per view, from a JSON list (or {"angles_deg": [...]}) or a text file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise click.BadParameter(f"{p}: cannot read it ({exc})", param_hint="--angles") from None
    try:
        doc = json.loads(text)
        values = doc.get("angles_deg") if isinstance(doc, dict) else doc
    except json.JSONDecodeError:
        values = text.replace(",", " ").split()
    try:
        return [float(v) for v in values]
    except (TypeError, ValueError):
        raise click.BadParameter(f"{p}: expected numbers (degrees), one per view", param_hint="--angles") from None


@click.command("import")
@click.argument("raw", type=click.Path(path_type=Path))
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="scan folder to write")
@click.option("--flats", type=click.Path(path_type=Path), default=None,
              help="flat fields (beam, no object): a file or folder of images, averaged")
@click.option("--darks", type=click.Path(path_type=Path), default=None,
              help="dark fields (no beam): a file or folder of images, averaged")
@click.option("--air-columns", default=None, metavar="FIRST,LAST",
              help="without flat fields: detector columns that see only air, for I0 "
                   "[default: the brightest 1 %% of each view]")
@click.option("--angles", "angles_file", type=click.Path(path_type=Path), default=None,
              help="a file of view angles in degrees, one per view (JSON list or text) [default: the file's own]")
@click.option("--arc", type=FiniteFloat(min=0, min_open=True, max=360), default=None,
              help="without angles: the views span this many degrees, evenly spaced")
@click.option("--mode", type=click.Choice(["parallel", "cone"]), default="parallel", show_default=True)
@distance_options("cone beam: source to axis, mm", "cone beam: source to detector, mm")
@click.option("--pixel", type=FiniteFloat(min=0, min_open=True), default=1.0, show_default=True,
              help="detector pixel size, mm (sets the scale of every length)")
@click.option("--centre", default="auto", show_default=True,
              help="column of the rotation axis (after crop and binning), 'auto' to find it, or 'middle'")
@click.option("--crop", default=None, metavar="R0,R1,C0,C1", help="keep rows R0:R1 and columns C0:C1")
@click.option("--bin", "binning", default="1", show_default=True, metavar="N or ROWS,COLS",
              help="average blocks of pixels")
@click.option("--floor", type=FiniteFloat(min=0, min_open=True, max=1, max_open=True), default=1e-6,
              show_default=True, help="smallest intensity ratio kept (dead and starved pixels)")
@click.option("--views", type=click.IntRange(min=1), default=None, help="keep this many evenly spaced views")
@click.option("--geometry", "geometry_file", type=click.Path(path_type=Path), default=None,
              help="a geometry JSON file (TIGRE names, or per-view 'vectors'; docs/formats.md) of the detector "
                   "after crop and binning: replaces --angles, --arc, --mode, --DSO, --DSD, --pixel and --centre")
@click.option("--force", is_flag=True, help="overwrite an existing --out")
def import_raw(raw, out, flats, darks, air_columns, angles_file, arc, mode, DSO, DSD, pixel, centre, crop, binning,
               floor, views, geometry_file, force):
    """Turn RAW detector images into a scan folder: HDF5 Data Exchange (.h5), a TIFF stack or
    folder of TIFFs, DICOM projections, or .npy counts (views, rows, columns).

    Flat/dark correction and -log (floored pixels counted), optional crop and binning, the view
    angles, and the rotation axis (found from the projections, or given), then a circular
    geometry; the scan reconstructs with every method (clgs reconstruct SCAN ...)."""
    from clgs.io.raw import RawError, read_raw, scan_from_raw
    from clgs.io.scan import ScanError

    if out.exists() and not force:
        raise click.ClickException(f"{out} already exists; pass --force to overwrite it (or choose another --out)")
    if out.resolve() == raw.resolve() or raw.resolve() in out.resolve().parents:
        raise click.ClickException(f"--out {out} would write into the raw data {raw}; choose another folder")
    b = _ints(binning, 1, "N", "--bin") if "," not in str(binning) else _ints(binning, 2, "ROWS,COLS", "--bin")
    b = (b[0], b[0]) if len(b) == 1 else tuple(b)
    centre_value = {"auto": "auto", "middle": None}.get(str(centre).strip().lower(), centre)
    if centre_value not in ("auto", None):
        try:
            centre_value = float(centre_value)
        except ValueError:
            raise click.BadParameter(f"{centre!r}: give a column number, 'auto' or 'middle'",
                                     param_hint="--centre") from None
    try:
        data = read_raw(raw, flats=flats, darks=darks)
        scan, report = scan_from_raw(
            data, mode=mode, pixel=pixel, DSO=DSO, DSD=DSD,
            angles_deg=_angles(angles_file) if angles_file else None, arc_deg=arc, centre=centre_value,
            crop=_ints(crop, 4, "R0,R1,C0,C1", "--crop"), binning=b,
            air_columns=_ints(air_columns, 2, "FIRST,LAST", "--air-columns"), floor=floor, views=views,
            geometry=geometry_file)
        scan.save(out, overwrite=force)
    except (RawError, ScanError) as exc:
        raise click.ClickException(str(exc)) from None
    except OSError as exc:
        raise click.ClickException(f"could not write {out}: {exc}") from None
    g = scan.geometry
    c = report["centre"]
    click.echo(f"{raw}: {report['views']} views, flats {report['flats']}, darks {report['darks']} (I0 from "
               f"{report['I0']}); floored {report['floored_pixels']} pixels ({report['floored_fraction']:.2%}); "
               f"{report['brighter_than_flat_pixels']} brighter than the flat set to 0 "
               f"(down to {report['most_negative']:.3g})")
    if c["column"] is None:
        click.echo(f"geometry from {geometry_file} ({'circular' if g.is_circular else 'per-view vectors'})")
    else:
        click.echo(f"rotation axis at column {c['column']:.2f} ({c['method']}"
                   + (f", residual {c['rms_residual_pixels']:.2f} px" if "rms_residual_pixels" in c else "")
                   + f"): offDetector {g.offDetector[1]:.3f} mm")
    click.echo(f"wrote {out}: {scan.n_views} {g.mode}-beam views of {g.nDetector[0]} x {g.nDetector[1]} pixels, "
               f"volume {'x'.join(map(str, g.nVoxel))} voxels of {g.dVoxel[2]:.4g} mm")
