"""``clgs reconstruct``: any registered method on a scan folder, with its options before or after SCAN. Heavy
modules load when it runs."""
from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path

import click

from clgs.anatomy.record import MAX_CLOSING
from clgs.cli.common import (
    check_not_input,
    check_output,
    check_writable,
    claim_output,
    click_error,
    exit_if_interrupted,
    fmt_number,
    is_out_of_memory,
    is_volume_path,
    load_scan,
    new_folders,
    out_of_memory,
    remove_empty,
)
from clgs.cli.options import FiniteFloat, check_option_values, force_option, method_params, out_option
from clgs.cli.verbosity import detail, info, is_verbose

METHOD_KEY = "clgs.reconstruct.method"  # ctx.meta: (method record or None, its click options)


def _peek_method(args) -> str | None:
    """The ``--method``/``-m`` value among the command's words (before ``--``), if any: the
    method's options are known only once the method is, wherever they stand."""
    for i, word in enumerate(args):
        if word == "--":
            break
        if word in ("--method", "-m") and i + 1 < len(args):
            return args[i + 1]
        if word.startswith("--method="):
            return word.split("=", 1)[1]
        if word.startswith("-m") and not word.startswith("--") and len(word) > 2:
            return word[2:]
    return None


class _ReconstructCommand(click.Command):
    """The chosen method's options are options of the command itself (before or after SCAN):
    the method is read from the words first, then its options join the command's for parsing."""

    def prepare(self, ctx, args) -> None:
        """Make the method named in ``args`` and its options known to ``ctx``."""
        from clgs import methods

        try:
            ctx.meta[METHOD_KEY + ".named"] = _peek_method(args) is not None
            method = methods.get(_peek_method(args) or "fdk")
            ctx.meta[METHOD_KEY] = (method, method_params(method))
        except (methods.MethodError, ImportError, LookupError):  # the callback says what is wrong
            ctx.meta[METHOD_KEY] = (None, [])

    def get_params(self, ctx):
        return super().get_params(ctx) + list(ctx.meta.get(METHOD_KEY, (None, []))[1])

    def parse_args(self, ctx, args):
        self.prepare(ctx, args)
        try:
            return super().parse_args(ctx, args)
        except click.NoSuchOption as exc:
            method, params = ctx.meta[METHOD_KEY]
            if method is None:  # an unknown --method explains an unknown option best
                raise click.BadParameter(f"unknown method {_peek_method(args)!r}", ctx, param_hint="--method") from None
            known = ", ".join(o for p in params for o in p.opts + p.secondary_opts) or "none"
            raise click.UsageError(f"{exc.format_message()} (options of --method {method.name}: {known}; "
                                   f"see 'clgs reconstruct --method {method.name} --help')", ctx) from None

    def invoke(self, ctx):
        """The method's options go to the run (``ctx.meta``), the command's to the callback."""
        _, params = ctx.meta.get(METHOD_KEY, (None, []))
        ctx.meta[METHOD_KEY + ".values"] = {p.name: ctx.params.pop(p.name, None) for p in params}
        return super().invoke(ctx)

    def format_options(self, ctx, formatter):
        method, params = ctx.meta.get(METHOD_KEY, (None, []))
        own = [p.get_help_record(ctx) for p in super().get_params(ctx)]
        with formatter.section("Options"):
            formatter.write_dl([r for r in own if r])
        if method is not None and ctx.meta.get(METHOD_KEY + ".named"):
            records = [p.get_help_record(ctx) for p in params]
            with formatter.section(f"Options of --method {method.name}"):
                formatter.write_dl([r for r in records if r] or [("(none)", "")])

    def format_epilog(self, ctx, formatter):
        from clgs import methods

        with formatter.section("Methods"):
            formatter.write_dl(sorted(methods.describe().items()))
        formatter.write_paragraph()
        formatter.write_text("Method options (before or after SCAN): see 'clgs reconstruct --method NAME --help'.")


def _method_command(method) -> click.Command:
    """A command holding only the method's options (their checks; the docs' checks parse with it)."""
    return click.Command(f"reconstruct --method {method.name}", params=method_params(method),
                         help=method.help, add_help_option=False)


def _method_options(ctx, method, mcmd) -> tuple:
    """(options given, keyword arguments of the run) from the method's options, checked."""
    values = ctx.meta.get(METHOD_KEY + ".values", {})
    try:  # NaN / inf floats and impossible seeds are refused now, whatever type the method's options declared
        check_option_values(mcmd.params, values, ctx)
    except click.UsageError as exc:
        raise click.UsageError(exc.format_message(), ctx) from None
    options = {k: v for k, v in values.items() if v is not None}
    kwargs = dict(options)
    if options.get("resume") and "iterations" in values and "iterations" not in options:
        kwargs["iterations"] = None  # a resumed run goes on to the iterations it was started with
    return options, kwargs


def _merge_settings(method, pairs, options: dict, kwargs: dict) -> None:
    """``--set KEY=VALUE`` pairs checked as ``clgs <anatomy> reconstruct`` checks them, added to
    the run's options; a setting given both ways is a usage error."""
    from clgs.cli.settings import check_settings, parse_settings

    raw: dict = {}
    extra = check_settings(method.name, method, method.callable(), parse_settings(pairs, raw), raw)
    clash = sorted(set(extra) & set(options))
    if clash:
        raise click.UsageError(f"{', '.join(clash)} given both as an option and with --set; give it once")
    options.update(extra)
    kwargs.update(extra)


def _prepare_outputs(scan, out, json_out, force, into_folder: bool, resuming: bool) -> tuple:
    """Check every output location before the run, so no result is lost at the end; returns the
    folders this command creates (removed again if the run fails before writing in them)."""
    check_not_input(out, [("scan", scan, True)])
    if json_out is not None:
        check_not_input(json_out, [("scan", scan, True)], "--json")
        if Path(json_out).resolve() == Path(out).resolve():
            raise click.UsageError("--json and --out name the same file; give the report another name")
    check_output(out, force, resume=resuming)
    if json_out is not None:
        check_output(json_out, force, "--json")
    check_writable(out, into=into_folder and out.is_dir())
    if json_out is not None:
        check_writable(json_out, "--json")
    created = new_folders(out if into_folder else Path(os.path.abspath(out)).parent)
    created_json = new_folders(Path(os.path.abspath(json_out)).parent) if json_out is not None else []
    return created, created_json


@click.command(cls=_ReconstructCommand, add_help_option=False)
@click.argument("scan", type=click.Path(path_type=Path), required=False)
@click.option("--method", "-m", "method_name", default="fdk", show_default=True, help="reconstruction method")
@out_option(type=click.Path(path_type=Path),
            help="a volume file (.nii.gz, .nii, .npy) or a folder (volume.nii.gz, volume.npy, report.json, "
                   "method extras)")
@click.option("--split", type=click.Choice(["train", "test"]), default="train", show_default=True,
              help="which views of an R2-Gaussian dataset folder to use")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="also write the report (method, options, time, metrics) to this JSON file")
@force_option("replace an existing --out (and --json)")
@click.option("--to-hu", "hu", is_flag=True,
              help="write the volume in Hounsfield units, at the X-ray energy the scan records (a simulation of a "
                   "CT with `simulate --hu`) or --kev [default: attenuation, 1/mm]")
@click.option("--kev", type=FiniteFloat(min=40, max=150), default=None,
              help="X-ray energy (keV) for --to-hu, when the scan records none (water's attenuation from NIST XCOM)")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="a method setting, as clgs <anatomy> reconstruct takes them (repeatable); the method's own "
                   "options after SCAN say the same")
@click.option("--surface-level", type=FiniteFloat(min=0, min_open=True), default=None,
              help="bone level (1/mm): also write OUT/surface.stl, the volume's outer bone surface there [default: "
                   "the level the scan's true surface was made at, if it names one; else no surface]")
@click.option("--surface-closing", type=click.IntRange(0, MAX_CLOSING), default=None, metavar="VOXELS",
              help="seal gaps in the bone's wall up to this many voxels wide before OUT/surface.stl is taken (a "
                   "thin cortex below the level opens the marrow canal to the outside; docs/outputs.md) "
                   f"[default: the closing of the anatomy the scan names (femur: 3), else 0; at most {MAX_CLOSING}]")
@click.option("--help", "-h", "show_help", is_flag=True, help="show this message (with --method: its options)")
@click.pass_context
def reconstruct(ctx, scan, method_name, out, split, json_out, force, hu, kev, settings, surface_level,
                surface_closing, show_help):
    """Reconstruct a volume from SCAN (a clgs scan folder or an R2-Gaussian dataset folder).

    The volume is attenuation in 1/mm (Hounsfield units with --to-hu), in the array order and with
    the affine of the volume the scan was simulated from. With a ground truth in the scan, prints
    3D PSNR / SSIM (as R2-Gaussian computes them, in 1/mm) and the wall time. A folder OUT also
    gets slices.png (central slices; with a truth, the truth's and the error's) and, at a bone
    level (--surface-level, or the one the scan records), surface.stl with its distance to the
    scan's true surface; `clgs <anatomy> reconstruct` takes the anatomy's level (docs/outputs.md).
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
        click.echo(ctx.get_help())
        ctx.exit(0)
    if scan is None:
        raise click.UsageError("missing argument SCAN (a scan folder)")
    if out is None:
        raise click.UsageError("missing option --out (a volume file or a folder)")
    if kev is not None and not hu:
        raise click.UsageError("--kev is the energy of --to-hu's Hounsfield units: add --to-hu, or leave out --kev")
    options, kwargs = _method_options(ctx, method, mcmd)
    if settings:
        _merge_settings(method, settings, options, kwargs)
    if options.get("resume") and force:
        raise click.UsageError("--resume continues the run in --out, --force replaces it: give one")
    if surface_level is not None and is_volume_path(out):
        raise click.UsageError("--surface-level writes OUT/surface.stl next to the volume: give a folder as --out")
    if surface_closing is not None and is_volume_path(out):
        raise click.UsageError("--surface-closing seals OUT/surface.stl, written next to the volume: give a folder "
                               "as --out")
    if surface_level is not None and _takes_surface_level(method):
        kwargs["surface_level"] = surface_level  # a method that writes its own bone surface
    if surface_closing is not None and _takes_surface_level(method):
        from clgs.methods.run import check_surface_closing

        try:  # run_method's rule, before the outputs are claimed
            check_surface_closing(method, surface_closing)
        except methods.MethodError as exc:
            raise click.UsageError(str(exc)) from None
        kwargs["surface_closing"] = surface_closing
    into_folder = not is_volume_path(out) and not method.atomic_dir
    resuming = bool(options.get("resume")) and into_folder and out.is_dir()
    created, created_json = _prepare_outputs(scan, out, json_out, force, into_folder, resuming)

    import numpy as np

    from clgs.io import atomic
    from clgs.io.reconstruction import output_units, save_reconstruction
    from clgs.io.units import UnitsError

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

            figures = metrics.volume_figures(vol, sc.truth)
            if figures["psnr3d"] is not None:
                s, axes = metrics.ssim3d(vol, sc.truth, return_axes=True)
                figures.update(ssim3d=s, ssim3d_axes=axes)
            report["metrics"] = figures
        save_reconstruction(out if folder is None else folder, vol, sc.geometry, hu=hu, kev=kev, meta=sc.meta,
                            folder=folder is not None)
        if folder is not None:
            report.update(run_figures(folder, vol, sc, method.name, surface_level, result.get("info") or {},
                                      surface_closing))
            # the folder's files named in the report are where they end up (an atomic folder is renamed)
            for key in ("slices", "surface"):
                if report.get(key, {}).get("path"):
                    report[key]["path"] = str(Path(out) / Path(report[key]["path"]).name)
            atomic.write_json(folder / "report.json", report)

    t_start = time.perf_counter()
    sc = None
    report = {"method": method.name, "options": options, "scan": str(scan)}
    claimed = contextlib.ExitStack()  # the lock on --out, held until the report is written
    try:
        claimed.enter_context(claim_output(out, force, resume=resuming))
        from clgs.progress import enabled

        claimed.enter_context(enabled(kwargs.get("progress", True)))  # --no-progress: no phase lines either
        try:
            sc = load_scan(scan, split)
            report["n_views"] = sc.n_views
            report["scan_path"] = str(Path(scan).resolve())
            from clgs.io.dicom_identity import scan_identity

            report["scan_identity"] = scan_identity(sc)  # the study and frame its DICOM series join
            try:  # before the run: an unknown energy must not cost a reconstruction
                report["volume_units"] = output_units(hu, kev, sc.meta)
            except UnitsError as exc:
                raise click.UsageError(str(exc)) from None
            report["volume_orientation"] = sc.geometry.orientation
            from clgs.anatomy.bone_level import choose_level

            if (surface_closing is not None and not _takes_surface_level(method)
                    and choose_level(user=surface_level, scan_meta=sc.meta) is None):  # before the run
                raise click.UsageError("--surface-closing seals the bone surface, which is written at a bone level: "
                                       "the scan names none, so give --surface-level too")
            info(f"{method.name}: {sc.n_views} views, {'x'.join(map(str, sc.geometry.nVoxel))} voxels")
            if is_verbose():
                _say_detail(method, options, sc, time.perf_counter() - t_start)
            try:
                method.callable()
            except (ImportError, AttributeError) as exc:
                raise click.ClickException(f"method {method.name!r} could not be loaded: {exc}") from None
            from clgs.methods.run import run_method

            def run(scan_, folder):
                """The one way to run a method (the settings were checked above); ``--anatomy``
                is no setting but the anatomy the run is given (the shape method's option)."""
                settings = dict(kwargs)
                return run_method(method, scan_, folder, settings, anatomy=settings.pop("anatomy", None))

            if is_volume_path(out):
                t0 = time.perf_counter()
                finish(run(sc, None), t0, None)
            elif method.atomic_dir:
                with atomic.atomic_dir(out, overwrite=force) as tmp:
                    t0 = time.perf_counter()
                    finish(run(sc, tmp), t0, tmp)
            else:
                out.mkdir(parents=True, exist_ok=True)
                t0 = time.perf_counter()
                finish(run(sc, out), t0, out)
        except (MemoryError, RuntimeError) as exc:
            if not is_out_of_memory(exc):
                raise
            if sc is None:
                raise out_of_memory(f"to load the scan {scan}") from None
            raise out_of_memory(f"for {method.name}", sc.geometry.nVoxel) from None
        except (ValueError, OSError, FloatingPointError) as exc:
            raise click_error(exc, f"{method.name} failed") from None
    except BaseException:  # errors and Ctrl-C alike: no empty output folder stays behind
        claimed.__exit__(*sys.exc_info())
        remove_empty(created)
        remove_empty(created_json)
        raise
    if json_out is not None:
        try:
            atomic.write_json(json_out, report)
        except OSError as exc:
            raise click.ClickException(f"wrote {out}, but the report could not be written to --json {json_out}: "
                                       f"{exc}") from None
        finally:
            claimed.close()
    claimed.close()
    line = f"{method.name}: {report['seconds']:.2f} s"
    if "metrics" in report:
        m = report["metrics"]
        if m.get("psnr3d") is None:
            line += f"; metrics undefined ({m.get('metrics_undefined')}); the volume is written"
        else:
            line += f", PSNR {fmt_number(m['psnr3d'])} dB, SSIM {m['ssim3d']:.4f}"
    detail(f"timings: {time.perf_counter() - t_start:.2f} s in all, {report['seconds']:.2f} s in the method")
    click.echo(line)
    click.echo(f"wrote {out}")
    for text in figure_lines(report):
        click.echo(text)
    exit_if_interrupted(report.get("info"))


def _say_detail(method, options: dict, scan, seconds: float) -> None:
    """``clgs --verbose``: the device, the settings the run uses, the time to load the scan."""
    import json

    try:
        from clgs.runtime import device

        detail(f"device: {device().name.strip()}")
    except Exception as exc:  # noqa: BLE001 - no OpenCL device: the method says so if it needs one
        detail(f"device: none ({exc})")
    detail(f"settings: {json.dumps(options, sort_keys=True, default=str) if options else '(the method defaults)'}")
    detail(f"scan loaded in {seconds:.2f} s ({scan.geometry.mode} beam, detector "
           f"{scan.geometry.nDetector[0]} x {scan.geometry.nDetector[1]})")


def _takes_surface_level(method) -> bool:
    """Whether the method's callable names a ``surface_level`` parameter (it writes its own bone surface)."""
    import inspect

    try:
        return "surface_level" in inspect.signature(method.callable()).parameters
    except (TypeError, ValueError, ImportError, AttributeError):
        return False


def _scan_anatomy_closing(scan) -> int:
    """The ``scene.surface_closing`` of the installed anatomy a scan names (``meta['anatomy']``,
    as ``clgs <anatomy> simulate`` writes it); 0 for any other scan."""
    from clgs.anatomy import plugins
    from clgs.anatomy.bone_level import anatomy_closing

    name = (scan.meta or {}).get("anatomy")
    if not isinstance(name, str) or name not in plugins.anatomy_names():
        return 0
    return anatomy_closing(plugins.get_anatomy(name))


def run_figures(folder, volume, scan, method_name: str, surface_level, info: dict, surface_closing=None) -> dict:
    """The run folder's slice panel and bone surface (written by the method itself when it names
    them in ``info``; else at ``surface_level`` or the scan's, its wall sealed by a closing of up to
    ``surface_closing`` voxels or the scan's anatomy's), with the surface's distance to the scan's
    true surface measured on the file read back: ``{"slices": {...}, "surface": {...}}`` for the
    report."""
    from clgs.anatomy.bone_level import choose_level, with_closing
    from clgs.anatomy.evaluation import LEVEL_KEYS, read_bone_surface, write_bone_surface
    from clgs.figures import SLICES_FILE, volume_slices

    out = {"slices": {"path": volume_slices(Path(folder) / SLICES_FILE, volume, scan.geometry, truth=scan.truth,
                                            title=f"{method_name}, {scan.n_views} views"),
                      "what": "central axial, coronal and sagittal slices" + (
                          "; the truth's and the error's below" if scan.truth is not None else "")}}
    if "surface_level_source" in info or "surface_note" in info:  # the method wrote (or ruled out) its own
        surface = {"path": info.get("surface_file"), "reason": info.get("surface_note"),
                   **{k: info[k] for k in LEVEL_KEYS if k in info}}
    else:
        level = choose_level(user=surface_level, scan_meta=scan.meta)
        if level is not None:  # the closing given, else a scan of an installed anatomy's: holes sealed as it asks
            closing = _scan_anatomy_closing(scan) if surface_closing is None else surface_closing
            level = with_closing(level, closing)
        surface = write_bone_surface(folder, volume, scan.geometry, level)
    surface = {k: v for k, v in surface.items() if v is not None}
    written = read_bone_surface(folder) if surface.get("path") else None
    if written is not None and scan.surface is not None:
        from clgs.metrics import surface_distance

        sd = surface_distance(written[0], scan.surface)
        surface.update({f"distance_{k}_mm": v for k, v in sd.items()})
    out["surface"] = surface
    return out


def figure_lines(report: dict) -> list:
    """What the run folder's figures and surface are, for the terminal."""
    lines = []
    slices = report.get("slices") or {}
    if slices.get("path"):
        lines.append(f"slices: {slices['path']}")
    s = report.get("surface") or {}
    if s.get("path"):
        text = (f"bone surface: {s['path']} (level {s['surface_level']:.4g} 1/mm, source: "
                f"{s['surface_level_source']})")
        if "distance_mean_mm" in s:
            text += (f"; to the true surface: mean {s['distance_mean_mm']:.3f} mm, p95 {s['distance_p95_mm']:.3f}, "
                     f"Hausdorff {s['distance_hausdorff_mm']:.3f}")
        lines.append(text)
    elif s.get("reason"):
        lines.append(f"bone surface: none written ({s['reason']})")
    return lines
