"""``clgs <anatomy> ...``: the same generic commands for every anatomy plugin.

    simulate      a held-out subject (--subject ID) or a surface file (--mesh FILE) -> scan folder
    reconstruct   a scan folder -> volume (method "shape" when the anatomy has a shape model, else r2gs)
    build-model   register the population, PCA, density atlas -> the model file
    evaluate      a reconstructed volume against the scan's truth: PSNR / SSIM / surface distance
    demo          simulate a held-out subject, reconstruct it, evaluate, print error vs time
    info          template size, model modes, variance kept, registration residuals

plus the plugin's own ``Anatomy.commands``. What the group expects from a plugin is the
:class:`clgs.anatomy.Anatomy` contract; commands whose loader is missing say so.

Only click is imported at module level; numpy/torch and the CT code load when a command runs.
"""
from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import click

from clgs.anatomy.record import MAX_CLOSING
from clgs.cli.cohort_options import check_cohort_options, cohort_options
from clgs.cli.common import check_memory, check_not_input, exit_if_interrupted
from clgs.cli.options import FiniteFloat, Seed, force_option, mesh_space_option, out_option
from clgs.cli.settings import check_settings, option_settings, parse_settings
from clgs.cli.verbosity import detail, info
from clgs.errors import ClgsError

# --------------------------------------------------------------------------------------- errors
# The library reports bad input with these (ValueError's subclasses: ScanError, ModelFileError,
# CheckpointError, MeshError, VolumeError, ...): every generic command turns them into a click
# error with the library's message (no traceback, non-zero exit). Anything else is a bug and keeps
# its traceback. Unknown subjects (KeyError) are caught where subjects are loaded (_load_subject),
# not here: a KeyError elsewhere is a programming error.
# FloatingPointError: a run whose loss or parameters turned NaN/Inf (the last good checkpoint is kept)
# ClgsError: every error of clgs about what it was given or where it writes (a full disk included)
INPUT_ERRORS = (ValueError, FileNotFoundError, FloatingPointError, ClgsError)


def _message(exc: BaseException) -> str:
    if isinstance(exc, FileNotFoundError) and exc.filename and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc) or type(exc).__name__


class AnatomyCommand(click.Command):
    """A generic anatomy command: the library's input errors (:data:`INPUT_ERRORS`) become click
    errors carrying the library's message."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except INPUT_ERRORS as exc:
            raise click.ClickException(_message(exc)) from exc


def _load_subject(anatomy, subject_id):
    """The anatomy's subject ``subject_id``; an unknown id is a usage error naming the known ones."""
    loader = _need(anatomy, "load_subject", "load a subject")
    try:
        return loader(subject_id)
    except KeyError as exc:
        held = anatomy.test_subjects() if anatomy.test_subjects is not None else []
        msg = exc.args[0] if exc.args and isinstance(exc.args[0], str) else f"unknown subject {subject_id!r}"
        raise click.BadParameter(f"{msg}" + (f" (held out: {', '.join(held)})" if held else ""),
                                 param_hint="--subject") from exc


def _need(anatomy, attr, what):
    fn = getattr(anatomy, attr, None)
    if fn is None:
        raise click.ClickException(f"the {anatomy.name} plugin ({anatomy.package or 'unknown package'}) provides no "
                                   f"{attr}: cannot {what}")
    return fn


# --------------------------------------------------------------------------------------- library
# (scan simulation and evaluation are library code: clgs.anatomy.simulation and clgs.anatomy.evaluation)
def _simulate(anatomy, subject, *args, **kwargs):
    """:func:`clgs.anatomy.simulation.simulate_subject` (its input errors become command errors in
    :class:`AnatomyCommand`)."""
    from clgs.anatomy.simulation import simulate_subject

    return simulate_subject(anatomy, subject, *args, **kwargs)


def _evaluate(anatomy, scan, volume, folder=None) -> dict:
    """:func:`clgs.anatomy.evaluation.evaluate_volume` (input errors: see :class:`AnatomyCommand`) of
    the bone surface ``folder`` holds (``surface.stl``, read back from disk, at the level its
    ``surface.json`` names), so the figure printed is the file's; without one, of the surface taken
    from the volume at the anatomy's level (not written: ``surface_file`` says so). Plus, when
    ``folder`` holds a shape-guided run's ``shape_surface.stl`` (the template moved by the fitted
    shape coefficients), that surface's distance to the truth."""
    from clgs.anatomy.evaluation import SURFACE_FILE, evaluate_volume, read_bone_surface

    written = read_bone_surface(folder) if folder else None
    mesh, level = written if written is not None else (None, None)
    out = evaluate_volume(anatomy, scan, volume, surface=mesh, level=level)
    if scan.surface is not None:
        out["surface_file"] = (os.path.join(folder, SURFACE_FILE) if written is not None
                               else "not written (taken from the volume for this evaluation)")
    model = os.path.join(folder, "shape_surface.stl") if folder else None
    if model and os.path.isfile(model) and scan.surface is not None:
        from clgs.io.mesh import load_mesh
        from clgs.metrics import surface_distance

        sd = surface_distance(load_mesh(model, space="RAS"), scan.surface)  # clgs's own (tagged) file
        out.update({f"model_surface_{k}_mm": v for k, v in sd.items() if k in ("mean", "p95", "hausdorff")})
    return out


def _surface_picture(anatomy, scan, volume, folder) -> None:
    """FOLDER/surface_distance.png: the bone surface the folder holds (surface.stl, the one
    measured) and a shape-guided run's model surface, coloured by distance to the truth, when the
    scan has a true surface."""
    from clgs.anatomy.evaluation import read_bone_surface
    from clgs.anatomy.surface_figure import reconstruction_figure

    model = os.path.join(folder, "shape_surface.stl")
    model_mesh = None
    if os.path.isfile(model):
        from clgs.io.mesh import load_mesh

        model_mesh = load_mesh(model, space="RAS")  # clgs's own (tagged) file
    written = read_bone_surface(folder)
    if written is None and model_mesh is None:
        return
    png = reconstruction_figure(os.path.join(folder, "surface_distance.png"), anatomy, scan, volume, model_mesh,
                                mesh=None if written is None else written[0],
                                title=f"{anatomy.name} {scan.meta.get('subject', '')}".strip(),
                                level=None if written is None else written[1])
    if png:
        click.echo(f"  surface picture        {png}")


def default_method(anatomy) -> str:
    return "shape" if anatomy.load_shape_model is not None else "r2gs"


def method_accepts(method: str, option: str) -> bool:
    """Whether the registered method takes the setting ``option`` (False when unknown):
    :func:`clgs.methods.run.method_accepts`."""
    try:
        from clgs.methods.run import method_accepts as accepts

        return accepts(method, option)
    except Exception:  # noqa: BLE001 - unknown or unimportable: the run reports it properly
        return False


def _get_method(method: str):
    """(registry entry, its run callable); an unknown or broken method is a click error."""
    from clgs import methods

    try:
        m = methods.get(method)
        return m, m.callable()
    except LookupError as exc:
        raise click.ClickException(f"reconstruction method {method!r} is not available: {exc}") from exc
    except (ImportError, AttributeError) as exc:
        raise click.ClickException(f"reconstruction method {method!r} could not be loaded: {exc}") from exc


def run_reconstruct(scan, anatomy, method: str, out=None, surface_level=None, surface_closing=None, **options):
    """Reconstruct with a method of the registry through :func:`clgs.methods.run.run_method` (the
    anatomy goes to the methods that name an ``anatomy`` parameter). Returns
    the method's result dict (at least ``volume``). With ``out``, ``out/volume.npy`` is (over)written
    atomically with the volume just computed, whatever an earlier run left there (and
    ``out/volume.nii.gz`` for viewers), and so are the bone surface ``out/surface.stl`` (with
    ``surface.json``: the level and its source, :func:`clgs.anatomy.bone_level.choose_level`, or
    ``surface_level`` when given, its wall sealed by the anatomy's closing or ``surface_closing``; a
    method that writes its own, as the shape-guided one does, is given both) and the slice panel
    ``out/slices.png``; ``result["surface"]`` and ``result["slices"]`` record them."""
    from clgs.methods.run import run_method

    _get_method(method)  # an unknown or broken method: a click error
    result = run_method(method, scan, out, options, anatomy=anatomy, surface_level=surface_level,
                        surface_closing=surface_closing)
    if out is not None and "volume" in result:
        from clgs.anatomy.bone_level import choose_level, with_closing
        from clgs.anatomy.evaluation import LEVEL_KEYS, write_bone_surface
        from clgs.anatomy.simulation import as_float32
        from clgs.figures import SLICES_FILE, volume_slices
        from clgs.io.volume import save_volume

        os.makedirs(out, exist_ok=True)
        # always this run's volume (never an earlier run's): save_volume writes .npy files through
        # clgs.io.atomic.save_npy, so readers see the old file or the new one, never a torn one
        volume = as_float32(result["volume"])
        save_volume(os.path.join(out, "volume.npy"), volume, scan.geometry)
        save_volume(os.path.join(out, "volume.nii.gz"), volume, scan.geometry, units="1/mm")  # for viewers, in mm
        info = result.get("info") or {}
        if "surface_level_source" in info or "surface_note" in info:  # the method wrote (or ruled out) its own
            result["surface"] = {"path": info.get("surface_file"), "reason": info.get("surface_note"),
                                 **{k: info[k] for k in LEVEL_KEYS if k in info}}
        else:
            level = choose_level(user=surface_level, anatomy=anatomy, truth=scan.truth, scan_meta=scan.meta)
            result["surface"] = write_bone_surface(out, volume, scan.geometry, with_closing(level, surface_closing))
        result["slices"] = volume_slices(os.path.join(out, SLICES_FILE), volume, scan.geometry, truth=scan.truth,
                                         title=f"{anatomy.name}: {method}, {scan.n_views} views")
    return result


def _echo_outputs(result) -> None:
    """The bone surface written (and its level's source) and the slice panel."""
    surface = result.get("surface")
    if surface is not None:
        if surface.get("path"):
            sealed = surface.get("surface_closing_voxels")
            sealed = "" if sealed is None else (f"; gaps in its wall sealed by a {sealed}-voxel closing" if sealed else
                                                 "; no gap in its wall to seal")
            click.echo(f"  bone surface           {surface['path']} (level {surface['surface_level']:.4g} 1/mm, "
                       f"source: {surface['surface_level_source']}{sealed})")
        else:
            click.echo(f"  bone surface           none written: {surface.get('reason')}")
    if result.get("slices"):
        click.echo(f"  slices                 {result['slices']}")


def _geometry_views(path) -> int:
    """The number of views of a geometry file (its errors name the file: see AnatomyCommand)."""
    import json

    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (OSError, ValueError) as exc:
        raise click.BadParameter(f"{path}: not a readable JSON file ({exc})", param_hint="--geometry") from None
    doc = doc.get("geometry", doc) if isinstance(doc, dict) else doc
    views = doc.get("vectors", doc.get("angles")) if isinstance(doc, dict) else None
    if not isinstance(views, list) or not views:
        raise click.BadParameter(f"{path}: no 'vectors' or 'angles' list (one entry per view)", param_hint="--geometry")
    return len(views)


def _check_scan_memory(anatomy, views: int) -> None:
    """Refuse, before any work, a number of views whose projections (the anatomy's detector) would
    not fit in the memory available."""
    n_det = anatomy.scene.get("nDetector") if anatomy.scene else None
    if n_det:
        check_memory(f"{views} views of {n_det[0]} x {n_det[1]} pixels", 3.0 * 4 * views * n_det[0] * n_det[1],
                     "use fewer --views")


def _check_run_out(scan_dir, out, resume: bool, force: bool):
    """``clgs <anatomy> reconstruct``'s output folder: never the scan folder or inside it; one that
    holds anything needs --resume (continue its run) or --force (its clgs files go first); locked
    while the run writes it. Returns the claim (a context manager, :func:`clgs.io.outputs.claim`)."""
    from pathlib import Path

    from clgs.cli.common import claim_output

    if resume and force:
        raise click.UsageError("--resume continues the run in --out, --force replaces it: give one")
    check_not_input(Path(out), [("scan", Path(scan_dir), True)])
    scan_root, target = Path(scan_dir).resolve(), Path(out).resolve()
    if scan_root in target.parents:
        raise click.ClickException(f"--out {out} lies inside the scan folder {scan_dir}: a run's outputs may not go "
                                   "into its input; choose a folder outside it")
    return claim_output(Path(out), force, kind="folder", resume=resume)


def _echo_metrics(m: dict):
    for k, v in m.items():
        if isinstance(v, float):
            click.echo(f"  {k:22s} {v:.4f}")
        elif isinstance(v, (list, tuple)):
            click.echo(f"  {k:22s} " + " ".join(f"{x:.4f}" for x in v))
        else:
            click.echo(f"  {k:22s} {v}")


def _view_set_option(text):
    """``--angles``: None, or a :class:`clgs.anatomy.views.ViewSet` (a usage error otherwise)."""
    if text is None:
        return None
    from clgs.anatomy.views import CLINICAL_SETS, parse_degrees, view_set

    try:
        return view_set(text if text in CLINICAL_SETS else ",".join(str(d) for d in parse_degrees(text)) + ",")
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--angles") from exc


def _detector_option(text):
    """``--detector-mm``: None or (V, U) mm at the isocentre (a usage error otherwise)."""
    if text is None:
        return None
    import math

    try:
        vals = [float(x) for x in str(text).split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (1, 2) or not all(math.isfinite(v) and v > 0 for v in vals):
        raise click.BadParameter(f"{text!r}: give one or two positive sizes in mm, e.g. 300 or 300,300",
                                 param_hint="--detector-mm")
    return (vals[0], vals[-1])


MESH_SUFFIXES = (".stl", ".ply", ".obj", ".off", ".npz")


def _mesh_folder(folder, units: str, space=None) -> dict:
    """{id (file stem): (path, units, space)} of the surface files in ``folder``, sorted; a usage
    error when there is none or two share a stem."""
    files = sorted(p for p in os.listdir(folder) if p.lower().endswith(MESH_SUFFIXES)
                   and os.path.isfile(os.path.join(folder, p)))
    if not files:
        raise click.BadParameter(f"{folder} holds no surface file ({', '.join(MESH_SUFFIXES)})", param_hint="--meshes")
    out = {}
    for name in files:
        stem = os.path.splitext(name)[0]
        if stem in out:
            raise click.BadParameter(f"{folder}: two surfaces are called {stem!r}; rename one", param_hint="--meshes")
        out[stem] = (os.path.join(folder, name), units, space)
    return out


# --------------------------------------------------------------------------------------- group
def _simulate_command(anatomy) -> click.Command:
    """``clgs <anatomy> simulate``."""
    name = anatomy.name
    scene = anatomy.scene or {}

    @click.command(cls=AnatomyCommand)
    @option_settings("views", "arc", "angles", "detector_mm", "noise", "seed", "simulation",
                     owner=f"clgs {name} simulate")
    @click.option("--subject", "subject_id", help="subject id (held-out ones: see `info`)")
    @click.option("--mesh", type=click.Path(exists=True, dir_okay=False),
                  help="a surface file instead (mm, or see --units; either side, any frame)")
    @out_option("scan folder to write", required=True, type=click.Path(file_okay=False))
    @click.option("--views", default=int(scene.get("n_views", 50)), show_default=True, type=click.IntRange(min=1),
                  help="number of projections")
    @click.option("--arc", type=FiniteFloat(min=0, min_open=True, max=360), default=float(scene.get("arc_deg", 180.0)),
                  show_default=True, help="arc in degrees (0 < arc <= 360)")
    @click.option("--geometry", "geometry_file", type=click.Path(exists=True, dir_okay=False), default=None,
                  help="scanner and views from a geometry JSON (TIGRE names or per-view 'vectors', world mm; "
                       "docs/formats.md) instead of --views and --arc; the subject's grid replaces its volume")
    @click.option("--angles", default=None, metavar="DEG,DEG,...",
                  help="explicit view angles in degrees, e.g. 0,90 (lateral + AP), 0,45,90, or a named set: "
                       "ap-lat, ap-oblique-lat, carm5 (5 views over 90); replaces --views/--arc")
    @click.option("--detector-mm", default=None, metavar="MM[,MM]",
                  help="a smaller detector: its field of view at the isocentre in mm (V,U, or one number for a "
                       "square), e.g. 300 for a C-arm; the bone beyond it is truncated [default: sees it whole]")
    @click.option("--units", type=click.Choice(["mm", "cm", "m", "in"]), default="mm", show_default=True,
                  help="length unit of the --mesh file (rescaled to mm)")
    @mesh_space_option("--mesh")
    @click.option("--noise/--no-noise", default=True, show_default=True, help="Poisson + electronic noise")
    @click.option("--seed", type=Seed(), default=0, show_default=True, help="noise seed, 0 to 2**64 - 1")
    @force_option("replace an existing scan folder --out", aliases=("--overwrite",))
    @click.option("--simulation", "protocol", type=click.Choice(["fine", "same"]), default="fine", show_default=True,
                  help="fine: projections from a grid twice as fine as the reconstruction grid; same: on the "
                       "reconstruction grid itself (R2-Gaussian's protocol, flatters FDK and SART)")
    def simulate(subject_id, mesh, out, views, arc, geometry_file, angles, detector_mm, units, mesh_space, noise,
                 seed, force, protocol):
        """Simulate a CT scan of a subject (default: the first held-out one) or of a surface file."""
        import math

        if subject_id and mesh:
            raise click.UsageError("give --subject or --mesh, not both")
        if units != "mm" and not mesh:
            raise click.UsageError("--units is the unit of a --mesh file")
        if mesh_space and not mesh:
            raise click.UsageError("--mesh-space is the frame of a --mesh file")
        view_set = _view_set_option(angles)
        fov = _detector_option(detector_mm)
        if geometry_file:
            ctx = click.get_current_context()
            given = [f"--{p.replace('_', '-')}" for p in ("views", "arc", "angles", "detector_mm")
                     if ctx.get_parameter_source(p) == click.core.ParameterSource.COMMANDLINE]
            if given:
                raise click.UsageError(f"--geometry gives the views and the detector: leave out {' and '.join(given)}")
            views = _geometry_views(geometry_file)
        if view_set is not None:
            views = view_set.n_views
        _check_scan_memory(anatomy, views)
        if mesh:
            from clgs.anatomy.simulation import subject_from_mesh_file

            subject = subject_from_mesh_file(anatomy, mesh, seed=seed, units=units, space=mesh_space)
        else:
            if not subject_id:
                held = _need(anatomy, "test_subjects", "pick a held-out subject")()
                if not held:
                    raise click.UsageError("the plugin has no held-out subjects: give --subject or --mesh")
                subject_id = held[0]
            subject = _load_subject(anatomy, subject_id)
        scan = _simulate(anatomy, subject, views, math.radians(arc), noise, seed, protocol=protocol,
                         geometry_file=geometry_file, angles=None if view_set is None else view_set.radians,
                         detector_mm=fov)
        try:
            scan.save(out, overwrite=force)
        except FileExistsError:
            raise click.ClickException(f"{out} exists: pass --force to replace it") from None
        if geometry_file:
            what = f"{scan.n_views} views from {geometry_file}"
        else:
            what = view_set.describe() if view_set is not None else f"{views} views over {arc:g} deg"
        g = scan.geometry
        click.echo(f"{name}: subject {subject.id} -> {out} ({what}, {'noisy' if noise else 'noiseless'}; "
                   f"grid {' x '.join(str(n) for n in g.nVoxel)} voxels, detector {g.nDetector[0]} x "
                   f"{g.nDetector[1]} pixels{' (truncated field of view)' if fov is not None else ''})")

    return simulate


def _reconstruct_command(anatomy) -> click.Command:
    """``clgs <anatomy> reconstruct``."""

    @click.command(cls=AnatomyCommand)
    @click.argument("scan_dir", type=click.Path(exists=True, file_okay=False))
    @out_option("output folder", required=True, type=click.Path(file_okay=False))
    @click.option("--method", default=None, help="shape (default with a shape model) | r2gs | fdk | sart | ...")
    @click.option("--views", default=None, type=click.IntRange(min=1),
                  help="use only this many of the scan's views, evenly spread [default: all]")
    @click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
                  help="method setting, e.g. iterations=3000 (repeatable; an unknown key lists the valid ones)")
    @click.option("--resume", is_flag=True,
                  help="continue the run in --out from its checkpoint, with its settings (same as --set "
                       "resume=true); without --set iterations=N it runs to the checkpoint's planned iterations")
    @force_option("replace what --out holds: an earlier clgs run's files are removed first (anything else "
                  "there is refused)")
    @click.option("--surface-level", type=FiniteFloat(min=0, min_open=True), default=None,
                  help="bone level (1/mm) of OUT/surface.stl [default: the anatomy's, or the truth's for a simulated "
                       "scan; docs/outputs.md]")
    @click.option("--surface-closing", type=click.IntRange(0, MAX_CLOSING), default=None, metavar="VOXELS",
                  help="seal gaps in the bone's wall up to this many voxels wide before OUT/surface.stl is taken "
                       "(0: none) [default: the anatomy's scene.surface_closing; docs/outputs.md]")
    def reconstruct(scan_dir, out, method, views, settings, resume, force, surface_level, surface_closing):
        """Reconstruct a scan folder with the anatomy's prior; writes OUT/volume.nii.gz and OUT/volume.npy."""
        method = method or default_method(anatomy)
        m, run = _get_method(method)
        raw = {}
        opts = parse_settings(settings, raw)
        if resume:
            if opts.get("resume", True) is not True:
                raise click.UsageError(f"--resume contradicts --set resume={raw['resume']}")
            if not method_accepts(method, "resume"):
                raise click.UsageError(f"the {method} method cannot resume a run (it keeps no checkpoint)")
            opts["resume"] = True
        # no iterations unless given: a resumed run then goes on to its checkpoint's planned count
        opts = check_settings(method, m, run, opts, raw)
        from clgs.methods.run import MethodError, check_surface_closing

        try:  # run_method's rule, before anything is claimed
            check_surface_closing(m, surface_closing)
        except MethodError as exc:
            raise click.UsageError(str(exc)) from None
        from clgs.progress import enabled

        with _check_run_out(scan_dir, out, bool(opts.get("resume")), force), enabled(opts.get("progress", True)):
            result, scan = _reconstruct_into(anatomy, scan_dir, out, method, views, opts, surface_level,
                                             surface_closing)
        exit_if_interrupted(result.get("info"))

    return reconstruct


def _reconstruct_into(anatomy, scan_dir, out, method, views, opts, surface_level=None, surface_closing=None) -> tuple:
    """The run of ``clgs <anatomy> reconstruct`` in its claimed folder: (result, scan)."""
    from clgs.io.scan import Scan

    name = anatomy.name
    scan = Scan.load(scan_dir)
    if views is not None:
        if not 1 <= views <= scan.n_views:
            raise click.BadParameter(f"{views}: the scan {scan_dir} has {scan.n_views} views; give 1 to "
                                     f"{scan.n_views} (or leave --views out to use them all)",
                                     param_hint="--views")
        import numpy as np

        scan = scan.subset(np.linspace(0, scan.n_views, views, endpoint=False).astype(int))
    t0 = time.perf_counter()
    result = run_reconstruct(scan, anatomy, method, out=out, surface_level=surface_level,
                             surface_closing=surface_closing, **opts)
    seconds = time.perf_counter() - t0
    click.echo(f"{name}: {method} reconstruction of {scan.n_views} views in {seconds:.1f} s -> {out}")
    _echo_outputs(result)
    if scan.truth is not None and "volume" in result:
        _echo_metrics(_evaluate(anatomy, scan, result["volume"], out))
        _surface_picture(anatomy, scan, result["volume"], out)
    return result, scan


def _takes(fn, keyword: str) -> bool:
    import inspect

    params = inspect.signature(fn).parameters
    return keyword in params or any(p.kind == p.VAR_KEYWORD for p in params.values())


def _build_model_command(anatomy) -> click.Command:
    """``clgs <anatomy> build-model``."""
    name = anatomy.name

    @click.command("build-model", cls=AnatomyCommand)
    @out_option("model file (default: the plugin's)", name="out_path", type=click.Path(dir_okay=False))
    @click.option("--variance", type=float, default=None,
                  help="keep the fewest modes holding this fraction of the variance [0.95] ...")
    @click.option("--generalisation-tol", "generalisation_tol_mm", type=float, default=None,
                  help="... or past which one more mode improves leave-one-out generalisation by less than "
                       "this (mm; 0: the variance rule alone) [0.05]")
    @click.option("--n-modes", type=int, default=None, help="keep exactly this many modes (overrides the rule)")
    @click.option("--max-cells", type=int, default=None, help="velocity grid cells along the longest side")
    @force_option("rebuild the model file even if an up-to-date one exists")
    @cohort_options
    def build_model_cmd(out_path, variance, generalisation_tol_mm, n_modes, max_cells, force, workers, scheduler):
        """Register the population to the template, PCA of the velocities, density atlas; prints the
        model's figures, the modes kept and the subjects mirrored."""
        check_cohort_options(workers, scheduler)
        settings = {k: v for k, v in dict(variance=variance, n_modes=n_modes, max_cells=max_cells,
                                          generalisation_tol_mm=generalisation_tol_mm).items()
                    if v is not None}
        if workers or scheduler:
            from clgs.cohort.registration import registration_runner
            from clgs.experiment import anatomy_by_name

            settings["run_registrations"] = registration_runner(anatomy_by_name(anatomy), workers or None, scheduler,
                                                                echo=info)
        t0 = time.perf_counter()
        if anatomy.build_model is not None:
            if "run_registrations" in settings and not _takes(anatomy.build_model, "run_registrations"):
                raise click.UsageError(f"the {name} plugin's build_model takes no run_registrations: it cannot "
                                       "register on --workers/--scheduler; build without them")
            kwargs = dict(settings, force=force)
            if out_path:
                kwargs["out_path"] = out_path
            path = anatomy.build_model(**kwargs)
        else:
            from functools import partial

            from clgs.shape.builder import build_model

            target = out_path or anatomy.model_path
            if not target:
                raise click.ClickException(f"the {name} plugin names no model_path: pass --out FILE")
            ids = _need(anatomy, "population", "list the population")()
            loader = _need(anatomy, "load_subject", "load subjects")
            template = _need(anatomy, "load_template", "load the template")()
            path = build_model(template, {sid: partial(loader, sid) for sid in ids}, target, force=force, **settings)
        click.echo(f"{name}: model {path} ready ({time.perf_counter() - t0:.1f} s)")
        chosen = {k: v for k, v in settings.items() if k != "run_registrations"}
        if not out_path and chosen:  # the plugin's own file now holds a model of other settings
            given = ", ".join(f"{k}={v}" for k, v in sorted(chosen.items()))
            click.echo(f"note: the {name} plugin's model file now holds a model built with {given}: every {name} "
                       f"command uses it from now on; `clgs {name} build-model` without them builds the default "
                       "again (--out FILE keeps a model apart)", err=True)
        from clgs.shape.model import read_metadata
        from clgs.shape.report import model_lines

        for line in model_lines(read_metadata(path)):
            click.echo(f"  {line}")

    return build_model_cmd


def _evaluate_command(anatomy) -> click.Command:
    """``clgs <anatomy> evaluate``: VOLUME then SCAN, the order of every evaluate (result, then truth)."""
    @click.command(cls=AnatomyCommand)
    @click.argument("volume", type=click.Path(exists=True))
    @click.argument("scan_arg", metavar="SCAN", required=False, type=click.Path(exists=True))
    @click.option("--truth", "-t", "truth", type=click.Path(exists=True, file_okay=False), default=None,
                  help="the scan folder holding the truth (the same as SCAN)")
    @out_option("also write the figures to this JSON file", type=click.Path(dir_okay=False))
    @force_option("replace an existing --out")
    def evaluate(volume, scan_arg, truth, out, force):
        """Compare a reconstructed VOLUME (.npy/.nii[.gz], or a run folder with volume.npy) with the truth
        of the scan folder SCAN."""
        from clgs.cli.common import check_evaluate_order
        from clgs.io.scan import Scan
        from clgs.io.volume import load_volume

        if scan_arg is not None and truth is not None:
            raise click.UsageError("give the scan once: as SCAN or as --truth")
        scan_dir = scan_arg or truth
        if scan_dir is None:
            raise click.UsageError("missing argument SCAN (the scan folder holding the truth): "
                                   f"clgs {anatomy.name} evaluate VOLUME SCAN")
        check_evaluate_order(volume, scan_dir, f"clgs {anatomy.name} evaluate VOLUME SCAN")
        if not os.path.isdir(scan_dir):
            raise click.BadParameter(f"{scan_dir}: not a scan folder", param_hint="SCAN")
        if out is not None:
            from pathlib import Path

            from clgs.cli.common import check_output, check_writable

            check_not_input(Path(out), [("volume", Path(volume), False), ("scan", Path(scan_dir), True)])
            check_output(Path(out), force, kind="file")
            check_writable(Path(out))
        if os.path.isdir(volume):
            volume = os.path.join(volume, "volume.npy")
        scan = Scan.load(scan_dir)
        loaded = load_volume(volume)
        vol = loaded[0]
        if str(volume).lower().endswith(".npy"):  # written in the scan's file order: back to the working one
            from clgs.io.orientation import to_working

            vol = to_working(vol, scan.geometry.orientation)
        # a run folder's surfaces are its volume's: another volume file lying there is measured alone
        run_volume = os.path.basename(volume) in ("volume.npy", "volume.nii.gz")
        figures = _evaluate(anatomy, scan, vol, os.path.dirname(volume) if run_volume else None)
        _echo_metrics(figures)
        if out is not None:
            from clgs.io import atomic

            atomic.write_json(out, {**figures, "volume": str(volume), "scan": str(scan_dir)}, overwrite=True)
            click.echo(f"wrote {out}")

    return evaluate


def _demo_command(anatomy) -> click.Command:
    """``clgs <anatomy> demo``."""

    @click.command(cls=AnatomyCommand)
    @click.option("--subject", "subject_id", default=None, help="held-out subject (default: the first)")
    @click.option("--views", default=5, show_default=True, type=click.IntRange(min=1))
    @click.option("--method", default=None, help="default: shape when the anatomy has a model, else r2gs")
    @out_option("keep outputs here (OUT/scan, OUT/recon) [default: a new temporary folder]",
                type=click.Path(file_okay=False))
    @click.option("--iterations", default=600, show_default=True, type=click.IntRange(min=1),
                  help="optimisation steps for iterative methods (the papers use 30000: hours on a CPU; "
                       "the shape-guided method peaks near 600 on the femur, see docs/results.md)")
    @click.option("--seed", type=Seed(), default=0, show_default=True, help="random seed, 0 to 2**64 - 1")
    @click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
                  help="method setting, e.g. tau=0.5 (repeatable; an unknown key lists the valid ones)")
    @click.option("--surface-level", type=FiniteFloat(min=0, min_open=True), default=None,
                  help="bone level (1/mm) of the surface written and measured [default: the truth's]")
    @force_option("replace an earlier demo's OUT/scan and OUT/recon (their clgs files only; anything else "
                  "there is refused)")
    def demo(subject_id, views, method, out, iterations, seed, settings, surface_level, force):
        """Simulate a held-out subject, reconstruct it from few views, print error vs time."""
        held = _need(anatomy, "test_subjects", "pick a held-out subject")()
        subject_id = subject_id or (held[0] if held else None)
        if subject_id is None:
            raise click.UsageError("the plugin has no held-out subjects: give --subject")
        method = method or default_method(anatomy)
        m, run = _get_method(method)
        raw = {}
        opts = parse_settings(settings, raw)
        if method_accepts(method, "iterations"):
            opts.setdefault("iterations", iterations)
        opts = check_settings(method, m, run, opts, raw)  # before the simulation: fail fast
        t0 = time.perf_counter()
        _check_scan_memory(anatomy, views)
        subject = _load_subject(anatomy, subject_id)  # a wrong subject or size is refused before OUT is touched
        with contextlib.ExitStack() as claims:
            from clgs.progress import enabled

            claims.enter_context(enabled(opts.get("progress", True)))  # --set progress=false: no phase lines
            if out is not None:  # the output rule (docs/output-rule.md), checked and locked before any work
                from clgs.cli.common import claim_output

                claims.enter_context(claim_output(Path(out) / "scan", force, kind="scan"))
                claims.enter_context(claim_output(Path(out) / "recon", force, kind="folder"))
            _run_demo(anatomy, subject, views, method, out, seed, surface_level, opts, t0)

    return demo


def _run_demo(anatomy, subject, views, method, out, seed, surface_level, opts, t0) -> None:
    """The work of ``clgs <anatomy> demo``, in its claimed folders (or a new temporary one)."""
    import math
    import tempfile

    name = anatomy.name
    scene = anatomy.scene or {}
    scan = _simulate(anatomy, subject, views, math.radians(float(scene.get("arc_deg", 180.0))), True, seed)
    info(f"{name} demo: subject {subject.id}, {views} views, method {method} "
               f"(simulated in {time.perf_counter() - t0:.1f} s)", err=False)
    work = out or tempfile.mkdtemp(prefix=f"clgs-{name}-demo-")
    scan.save(os.path.join(work, "scan"), overwrite=True)  # a new folder, or one claimed (and cleared) above
    t1 = time.perf_counter()
    result = run_reconstruct(scan, anatomy, method, out=os.path.join(work, "recon"), surface_level=surface_level,
                             **opts)
    elapsed = time.perf_counter() - t1
    history = result.get("history") or (result.get("info") or {}).get("history")
    if history:
        info("  iteration   time (s)   metrics", err=False)
        for logged in history:
            row = dict(logged)
            it, tt = row.pop("iteration", ""), row.pop("time", row.pop("seconds", float("nan")))
            info(f"  {it!s:>9} {tt:10.1f}   " + "  ".join(
                f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()), err=False)
    click.echo(f"reconstructed in {elapsed:.1f} s; final error (volume surface: the bone surface written):")
    _echo_metrics(_evaluate(anatomy, scan, result["volume"], os.path.join(work, "recon")))
    _echo_outputs(result)
    _surface_picture(anatomy, scan, result["volume"], os.path.join(work, "recon"))
    from clgs.bench.train import peak_memory_mib

    detail(f"peak resident memory: {peak_memory_mib():.0f} MiB")
    click.echo(f"outputs in {work}")
    exit_if_interrupted(result.get("info"))


def _experiment_command(anatomy) -> click.Command:
    """``clgs <anatomy> experiment``."""
    name = anatomy.name

    @click.command(cls=AnatomyCommand)
    @click.option("--views", multiple=True, type=click.IntRange(min=1),
                  help="view counts, e.g. --views 5 10 [default: 5 10]")
    @click.argument("more_views", nargs=-1, type=click.IntRange(min=1), metavar="")
    @click.option("--view-sets", "view_sets", multiple=True, metavar="SET",
                  help="clinical view sets, repeatable: ap-lat (0,90: lateral + AP), ap-oblique-lat (0,45,90), "
                       "carm5 (5 views over a 90-degree C-arm arc), or degrees such as 0,60,120")
    @click.option("--detector-mm", default=None, metavar="MM[,MM]",
                  help="every scan with a smaller detector: its field of view at the isocentre (mm), e.g. 300; "
                       "the bone beyond it is truncated")
    @click.option("--meshes", type=click.Path(exists=True, file_okay=False), default=None,
                  help="a folder of your own surfaces (STL/PLY/OBJ/OFF/npz, either side, any frame) to run the "
                       "protocol on instead of the held-out subjects")
    @click.option("--units", type=click.Choice(["mm", "cm", "m", "in"]), default="mm", show_default=True,
                  help="length unit of the --meshes files")
    @mesh_space_option("--meshes")
    @click.option("--tissue-seed", type=Seed(), default=None,
                  help="draw the tissue around every --meshes surface from this seed, so that surfaces changed "
                       "from one bone compare on the same limb [default: each surface's own, seeded by its name]")
    @click.option("--subjects", default=None, help="comma-separated held-out subject ids [default: all held out]")
    @click.option("--iterations", default=1000, show_default=True, type=click.IntRange(min=1),
                  help="training iterations of every Gaussian run (docs/results.md's tables: 1000, a few "
                       "minutes per subject on 2 cores; the paper: 30000, hours per run there)")
    @click.option("--ablation-views", default=5, show_default=True, type=click.IntRange(min=0),
                  help="view count of the ablation (0: none)")
    @out_option("experiment folder (an interrupted experiment resumes from it)", required=True,
                type=click.Path(file_okay=False))
    @click.option("--seed", type=Seed(), default=0, show_default=True, help="random seed, 0 to 2**64 - 1")
    @click.option("--log-every", default=500, show_default=True, help="evaluate every N iterations (curves)")
    @click.option("--simulation", "protocol", type=click.Choice(["fine", "same"]), default="fine", show_default=True,
                  help="fine: projections from a grid twice as fine as the reconstruction grid; same: on the "
                       "reconstruction grid itself (R2-Gaussian's protocol, flatters FDK and SART)")
    @click.option("--progress/--no-progress", default=True, help="progress bar per run")
    @cohort_options
    @click.option("--set", "shape_settings", multiple=True, metavar="KEY=VALUE",
                  help="a setting of every shape-guided run, e.g. residual=on (repeatable; recorded with each run)")
    @click.option("--schedule", type=click.Choice(["fast", "paper"]), default="fast", show_default=True,
                  help="the schedule of every Gaussian run: fast, the paper's cut at --iterations; paper, its decays "
                       "compressed into them (docs/schedules.md)")
    def experiment(views, more_views, view_sets, detector_mm, meshes, units, mesh_space, tissue_seed, subjects,
                   iterations,
                   shape_settings, schedule,
                   ablation_views, out, seed, log_every, progress, protocol, workers, scheduler):
        """The seed paper's experiment: R2-Gaussian vs shape-guided on every held-out subject,
        the ablation, error against run time, surfaces; writes table.md, results.csv, curves.png.
        Clinical view sets (--view-sets), a truncating detector (--detector-mm) and your own
        surfaces (--meshes) run the same protocol."""
        from clgs.experiment import run_experiment

        check_cohort_options(workers, scheduler)
        views = tuple(views) + tuple(more_views)  # `--views 5 10`: the 10 arrives as an argument
        sets = [_view_set_option(v) for v in view_sets]
        views = views + tuple(sets) if (views or sets) else (5, 10)
        fov = _detector_option(detector_mm)
        if mesh_space and not meshes:
            raise click.UsageError("--mesh-space is the frame of the --meshes files")
        if tissue_seed is not None and not meshes:
            raise click.UsageError("--tissue-seed draws the tissue around --meshes surfaces; the held-out subjects "
                                   "have their own")
        mesh_files = _mesh_folder(meshes, units, mesh_space) if meshes else None
        if mesh_files and subjects:
            raise click.UsageError("give --meshes or --subjects, not both")
        ids = [s.strip() for s in subjects.split(",")] if subjects else None
        if ids is not None:
            held = list(anatomy.test_subjects()) if anatomy.test_subjects is not None else []
            bad = [s for s in ids if s not in held]
            if bad:
                raise click.BadParameter(
                    f"{', '.join(repr(s) for s in bad)}: not held-out {name} subject(s); the experiment runs on "
                    f"held-out subjects only: {', '.join(held) if held else '(the plugin has none)'}",
                    param_hint="--subjects")
        per_run = {"log_every": log_every, "checkpoint_every": 0, "schedule": schedule}
        raw: dict = {}
        shape_opts = parse_settings(shape_settings, raw)
        if shape_opts:  # fail now, not in every run; checked as every --set is
            m, run = _get_method("shape")
            shape_opts = check_settings("shape", m, run, shape_opts, raw)
        summary = run_experiment(anatomy, out, views=views, subjects=ids, iterations=iterations,
                                 ablation_views=ablation_views or None, seed=seed, progress=progress,
                                 settings={"r2gs": per_run, "shape": {**per_run, **shape_opts}}, echo=info,
                                 workers=workers or None, scheduler=scheduler, simulation=protocol, detector_mm=fov,
                                 meshes=mesh_files, tissue_seed=tissue_seed)
        with open(os.path.join(out, "table.md"), encoding="utf-8") as f:
            click.echo(f.read())
        for v, g in summary["gain_db"].items():
            click.echo(f"{v}{' views' if str(v).isdigit() else ''}: shape-guided minus R2-Gaussian "
                       f"{g['mean']:+.2f} dB (ahead on {g['subjects_ahead']}/{g['subjects']} subjects)")
        if summary.get("stop_signal"):
            import signal

            sig = int(summary["stop_signal"])
            click.echo(f"experiment stopped by {signal.Signals(sig).name}: the finished runs are kept in {out}/runs, "
                       "the one going on was dropped; the same command resumes the experiment", err=True)
            raise SystemExit(128 + sig)
        if summary.get("failed"):
            raise click.ClickException(f"{len(summary['failed'])} run(s) failed (listed in {out}/table.md and "
                                       "summary.json); the others are done: run the same command again to retry them")

    return experiment


def _info_command(anatomy) -> click.Command:
    """``clgs <anatomy> info``."""
    name = anatomy.name

    @click.command(cls=AnatomyCommand)
    def info():
        """Template size, model modes, variance kept, registration residuals."""
        click.echo(f"{name}: {anatomy.summary}")
        click.echo(f"  package   {anatomy.package or '?'} {anatomy.version}")
        if anatomy.population is not None:
            click.echo(f"  population {len(anatomy.population())} subjects; held out: "
                       f"{', '.join(anatomy.test_subjects()) if anatomy.test_subjects else '-'}")
        if anatomy.load_template is not None:
            t = anatomy.load_template()
            ext = " x ".join(f"{e:.0f}" for e in t.extent_mm)
            click.echo(f"  template  grid {t.shape} (Z, Y, X) at {t.spacing[0]:g} mm ({ext} mm); "
                       f"surface {len(t.vertices)} vertices, {len(t.faces)} faces; "
                       f"volume {t.label.sum() * float(t.spacing[0] * t.spacing[1] * t.spacing[2]) / 1000:.1f} cm^3")
        path = anatomy.model_path
        built = bool(path) and os.path.exists(path)
        meta = {}
        if built:
            from clgs.shape.model import read_metadata

            meta = read_metadata(path)
        if not meta.get("statistics"):  # a model that records its figures is read, not recomputed
            _echo_shape_space(anatomy)
        if not built:
            click.echo(f"  model     not built ({path or 'no path'}): run `clgs {name} build-model`")
            return
        from clgs.shape.report import model_lines

        click.echo(f"  model     {path}")
        click.echo(f"            {meta.get('n_modes')} modes on grid {tuple(meta.get('grid_shape', ()))}, "
                   f"variance kept {100 * meta.get('variance_kept', float('nan')):.1f} %, "
                   f"{len(meta.get('population', []))} subjects")
        for line in model_lines(meta):
            click.echo(f"            {line}")
        res = meta.get("residuals") or {}
        if res:
            import numpy as np

            def stat(key):
                vals = [r[key] for r in res.values() if key in r]
                return (float(np.mean(vals)), float(np.max(vals))) if vals else (float("nan"),) * 2

            sm, sx = stat("surface_mean_mm")
            dm, _ = stat("dice")
            pm, px = stat("pca_rms_mm")
            click.echo(f"            registration: surface {sm:.2f} mm mean (worst subject {sx:.2f}), Dice {dm:.3f}; "
                       f"PCA residual {pm:.2f} mm RMS (worst {px:.2f})")
        if meta.get("has_atlas"):
            click.echo(f"            density atlas {tuple(meta.get('atlas_shape', ()))} from "
                       f"{meta.get('atlas_subjects')} CTs")
        elif meta.get("atlas_note"):
            click.echo(f"            {meta['atlas_note']}")

    return info


def _echo_shape_space(anatomy, max_modes: int = 5) -> None:
    """Compactness, generalisation and specificity of the population's surfaces
    (:mod:`clgs.shape.statistics`), for an anatomy whose surfaces are in vertex correspondence."""
    pop = getattr(anatomy, "population_model", None)
    if pop is None or anatomy.population is None or len(anatomy.population()) < 3:
        return
    import numpy as np

    from clgs.shape.statistics import shape_space_figures

    meshes = [pop.mesh(sid) for sid in anatomy.population()]
    if any(m[0].shape != meshes[0][0].shape for m in meshes):
        return  # not in correspondence: no vertex-level figures
    from clgs.shape.report import figure_lines

    f = shape_space_figures(np.stack([m[0] for m in meshes]), max_modes=max_modes, n_samples=100)
    first, *rest = figure_lines(f, f"PCA of the {len(meshes)} population surfaces' vertices")
    click.echo(f"  surfaces  {first}")
    for line in rest:
        click.echo(f"          {line}")


# the commands every anatomy gets, each made for one anatomy
GENERIC_COMMANDS = (_simulate_command, _reconstruct_command, _build_model_command, _evaluate_command, _demo_command,
                    _experiment_command, _info_command)


def make_group(anatomy) -> click.Group:
    """The click group ``clgs <anatomy.name>`` with the generic commands and the plugin's own."""
    name = anatomy.name

    @click.group(name=name, help=f"{anatomy.summary}\n\nPlugin: {anatomy.package or '?'} {anatomy.version}.")
    def group():
        pass

    for make in GENERIC_COMMANDS:
        group.add_command(make(anatomy))
    for cmd in anatomy.commands or []:
        if not isinstance(cmd, click.Command):
            raise click.ClickException(f"{name} plugin ({anatomy.package}): extra commands must be click commands, "
                                       f"got {type(cmd).__name__}")
        if cmd.name in group.commands:
            raise click.ClickException(f"{name} plugin ({anatomy.package}): command {cmd.name!r} clashes with a "
                                       "generic anatomy command")
        group.add_command(cmd)
    from clgs.anatomy import plugins

    plugins.registry().add_anatomy_commands(anatomy, group)  # hook register_anatomy_commands
    return group
