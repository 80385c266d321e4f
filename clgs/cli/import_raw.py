"""``clgs import``: raw detector images (counts) into a scan folder of line integrals."""
from __future__ import annotations

import json
from pathlib import Path

import click

from clgs.cli.options import FiniteFloat, distance_options, force_option, out_option


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
@out_option("scan folder to write", type=click.Path(path_type=Path), required=True)
@click.option("--flats", type=click.Path(path_type=Path), default=None,
              help="flat fields (beam, no object): a file or folder of images, averaged")
@click.option("--darks", type=click.Path(path_type=Path), default=None,
              help="dark fields (no beam): a file or folder of images, averaged")
@click.option("--air-columns", default="auto", show_default=True, metavar="A:B|auto|off",
              help="detector columns A to B-1 that see only air in every view: each view's I0 is set so that its "
                   "air reads 0 (also FIRST,LAST); 'auto' finds the air per view; 'off' keeps the flat field's I0")
@click.option("--angles", "angles_file", type=click.Path(path_type=Path), default=None,
              help="a file of view angles in degrees, one per view (JSON list or text) [default: the file's own]")
@click.option("--arc", type=FiniteFloat(min=0, min_open=True, max=360), default=None,
              help="without angles: the views span this many degrees, evenly spaced")
@click.option("--mode", type=click.Choice(["parallel", "cone"]), default="parallel", show_default=True)
@distance_options("cone beam: source to axis, mm", "cone beam: source to detector, mm")
@click.option("--pixel", type=FiniteFloat(min=0, min_open=True), default=1.0, show_default=True,
              help="detector pixel size, mm (sets the scale of every length)")
@click.option("--centre", default="auto", show_default=True,
              help="column of the rotation axis at the middle row (after crop and binning), 'auto' to find it "
                   "(every estimator, reported; docs/calibration.md), or 'middle'")
@click.option("--tilt", default=None, metavar="auto|DEG",
              help="apply a detector roll (in-plane tilt) through per-view vectors: 'auto' the one estimated from a "
                   "180-degree pair, or degrees [default: estimated and reported, not applied]")
@click.option("--rings", type=click.IntRange(min=3), default=None, metavar="SIZE",
              help="remove sinogram stripes (rings): sorting and a median across SIZE columns (odd, e.g. 21)")
@click.option("--zingers", default=None, metavar="auto|DIFF",
              help="remove zingers: pixels differing from their 3x3 median by more than DIFF (line integrals), "
                   "or 'auto' (8 robust standard deviations)")
@click.option("--crop", default=None, metavar="R0,R1,C0,C1", help="keep rows R0:R1 and columns C0:C1")
@click.option("--bin", "binning", default="1", show_default=True, metavar="N or ROWS,COLS",
              help="average blocks of pixels")
@click.option("--floor", type=FiniteFloat(min=0, min_open=True, max=1, max_open=True), default=1e-6,
              show_default=True, help="smallest intensity ratio kept (dead and starved pixels)")
@click.option("--views", type=click.IntRange(min=1), default=None, help="keep this many evenly spaced views")
@click.option("--geometry", "geometry_file", type=click.Path(path_type=Path), default=None,
              help="a geometry JSON file (TIGRE names, or per-view 'vectors'; docs/formats.md) of the detector "
                   "after crop and binning: replaces --angles, --arc, --mode, --DSO, --DSD, --pixel and --centre")
@force_option("replace an earlier scan folder in --out (its clgs files only; anything else there is refused)")
def import_raw(raw, out, flats, darks, air_columns, angles_file, arc, mode, DSO, DSD, pixel, centre, tilt, rings,
               zingers, crop, binning, floor, views, geometry_file, force):
    """Turn RAW detector images into a scan folder: HDF5 Data Exchange (.h5), a TIFF stack or
    folder of TIFFs, DICOM projections, or .npy counts (views, rows, columns).

    Flat/dark correction and -log (floored pixels counted), each view's I0 from its air, optional
    zinger and stripe removal, crop and binning, the view angles, and the rotation axis (found by
    three estimators whose agreement is reported, or given) and the detector's roll, then the
    geometry; the scan reconstructs with every method (clgs reconstruct SCAN ...)."""
    from clgs.cli.common import claim_output
    from clgs.io.raw import RawError, read_raw, scan_from_raw
    from clgs.io.scan import ScanError

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
    air, air_cols = _air(air_columns)
    tilt_value = _tilt(tilt)
    zinger_value = _zingers(zingers)
    if rings is not None and rings % 2 == 0:
        raise click.BadParameter(f"{rings}: give an odd number of columns", param_hint="--rings")
    # the output rule (docs/output-rule.md): refused without --force, cleared of an earlier scan's
    # files with it, locked while this import writes it
    with claim_output(out, force, kind="scan"):
        try:
            data = read_raw(raw, flats=flats, darks=darks)
            scan, report = scan_from_raw(
                data, mode=mode, pixel=pixel, DSO=DSO, DSD=DSD,
                angles_deg=_angles(angles_file) if angles_file else None, arc_deg=arc, centre=centre_value,
                crop=_ints(crop, 4, "R0,R1,C0,C1", "--crop"), binning=b,
                air_columns=air_cols, floor=floor, views=views, geometry=geometry_file, air=air, tilt=tilt_value,
                rings=rings, zingers=zinger_value)
            scan.save(out, overwrite=True)  # a new folder, or one claimed (and cleared) above
        except (RawError, ScanError) as exc:
            raise click.ClickException(str(exc)) from None
        except OSError as exc:
            raise click.ClickException(f"could not write {out}: {exc}") from None
    _echo_report(raw, scan, report, geometry_file, out)


def _air(value):
    """(normalise from the air?, (first, last exclusive) or None) from --air-columns."""
    text = str(value).strip().lower()
    if text == "auto":
        return True, None
    if text in ("off", "none"):
        return False, None
    if ":" in text:
        a, b = _ints(text.replace(":", ","), 2, "A:B", "--air-columns")
    else:
        a, b = _ints(text, 2, "FIRST,LAST", "--air-columns")
        b += 1
    return True, (a, b)


def _tilt(value):
    if value is None or str(value).strip().lower() == "auto":
        return value if value is None else "auto"
    try:
        return float(value)
    except ValueError:
        raise click.BadParameter(f"{value!r}: give 'auto' or degrees", param_hint="--tilt") from None


def _zingers(value):
    if value is None or str(value).strip().lower() == "auto":
        return value if value is None else "auto"
    try:
        v = float(value)
    except ValueError:
        v = float("nan")
    if not (v > 0 and v < float("inf")):
        raise click.BadParameter(f"{value!r}: give 'auto' or a positive difference", param_hint="--zingers")
    return v


def _echo_report(raw, scan, report, geometry_file, out):
    """Every figure the import measured, and a warning wherever they disagree."""
    g = scan.geometry
    c = report["centre"]
    click.echo(f"{raw}: {report['views']} views, flats {report['flats']}, darks {report['darks']} (I0 from "
               f"{report['I0']}); floored {report['floored_pixels']} pixels ({report['floored_fraction']:.2%}); "
               f"{report['brighter_than_flat_pixels']} still below 0 after normalisation set to 0 "
               f"(down to {report['most_negative']:.3g})")
    for note in report.get("notes", []):
        click.echo(f"  {note}")
    if report.get("floored_warning"):
        click.echo(f"warning: {report['floored_warning']}", err=True)
    air = report.get("air")
    if air is None:
        click.echo("air: not normalised (--air-columns off)")
    elif "background_min" in air:
        click.echo(f"air ({air['air']}): background removed per view {air['background_min']:.4f} to "
                   f"{air['background_max']:.4f} (mean {air['background_mean']:.4f}) in line-integral units; "
                   f"{air['air_columns_min']}-{air['air_columns_max']} air columns per view"
                   + (f", {air['views_without_air']} views without air (from their neighbours)"
                      if air["views_without_air"] else ""))
    else:
        click.echo(f"warning: air {air['note']}", err=True)
    if "zingers" in report:
        z = report["zingers"]
        click.echo(f"zingers: {z['pixels']} pixels ({z['fraction']:.3%}) replaced by their 3x3 median "
                   f"(threshold {z['threshold']:.3g}, {z['threshold_from']})")
    if "rings" in report:
        r = report["rings"]
        click.echo(f"rings: stripes removed ({r['method']}); mean change {r['mean_change']:.3g}, "
                   f"largest {r['max_change']:.3g}")
    if c["column"] is None:
        click.echo(f"geometry from {geometry_file} ({'circular' if g.is_circular else 'per-view vectors'})")
    else:
        click.echo(f"rotation axis at column {c['column']:.2f} ({c['method']}"
                   + (f"; {c['why']}" if "why" in c else "") + f"): offDetector {g.offDetector[1]:.3f} mm"
                   if g.is_circular else f"rotation axis at column {c['column']:.2f} ({c['method']})")
        for key, e in c.get("estimates", {}).items():
            click.echo("  " + _estimate_line(key, e))
        if "spread_pixels" in c and len(c["counted"]) > 1:
            click.echo(f"  the counted estimators {'agree' if c['agree'] else 'DISAGREE'}: spread "
                       f"{c['spread_pixels']:.2f} px")
        if c.get("warning"):
            click.echo(f"warning: {c['warning']}", err=True)
    t = report.get("tilt")
    if t and (t["estimated_deg"] is not None or t["applied_deg"] is not None):
        est = "" if t["estimated_deg"] is None else f"estimated {t['estimated_deg']:+.3f} deg ({t['from']})"
        app = ("applied " + f"{t['applied_deg']:+.3f} deg through per-view vectors") if t["applied_deg"] else \
            "not applied (--tilt auto applies it)"
        click.echo(f"detector roll: {est}{'; ' if est else ''}{app}")
    click.echo(f"wrote {out}: {scan.n_views} {g.mode}-beam views of {g.nDetector[0]} x {g.nDetector[1]} pixels, "
               f"volume {'x'.join(map(str, g.nVoxel))} voxels of {g.dVoxel[2]:.4g} mm")


def _estimate_line(key, e) -> str:
    name = f"{e['name']:<16}"
    if not e["available"]:
        return f"{name} not available: {e['why']}"
    if key == "pair":
        fig = f"mismatch {e['mismatch_percent']:.2f} %, views {' '.join('/'.join(map(str, p)) for p in e['pairs'][:3])}"
        fig += "" if abs(e["gap_deg"]) < 1e-6 else f" ({180 + e['gap_deg']:.4g} deg apart, interpolated)"
        fig += "" if e.get("tilt_deg") is None else f", roll {e['tilt_deg']:+.3f} deg"
    elif key == "sinogram":
        contrast = "n/a" if e["contrast_percent"] is None else f"{e['contrast_percent']:.0f} %"
        fig = f"contrast {contrast} (3 px either side), rows {','.join(map(str, e['rows']))}"
    else:
        fig = (f"rms residual {e['rms_residual_pixels']:.2f} px after removing the air background "
               f"({e['background_removed_min']:.3g} to {e['background_removed_max']:.3g})")
    line = f"{name} {e['column']:8.2f}  {fig}"
    if not e.get("counted", True):
        line += f"  [not counted: {e['why_not_counted']}]"
    if e.get("note"):
        line += f"  [{e['note']}]"
    return line
