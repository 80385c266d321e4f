"""The seed paper's experiment for any anatomy: R2-Gaussian against shape-guided reconstruction of
the held-out subjects at a few view counts, with the ablation, error against run time, and surfaces.

For every held-out subject and view count a scan is simulated (the anatomy's scanner, 0-180
degrees, noise on), then reconstructed by

* ``fdk``: the classical baseline (for reference);
* ``r2gs``: R2-Gaussian mode (FDK initialisation, densification);
* ``shape``: shape-guided (shape prior + density prior);

and, at the ablation's view count, ``init`` (shape-guided initialisation only: the Gaussians move
freely, no priors) and ``init+shape`` (bound to the shape model, no density prior). Each run is
scored with 3D PSNR / SSIM and the distance (mm) from its outer bone surface to the true one, and
its wall time is kept. Every finished run is saved at once (``runs/<subject>_<views>_<method>.json``
plus its surface STL), so an interrupted experiment resumes where it stopped.

Each run is an independent task (:mod:`clgs.cohort`): it simulates its scan (seeded), reconstructs
and writes its record itself, here or in a Dask worker process (``workers``, ``scheduler``); the
tables are gathered from the records. A run that fails is listed with its error, the others go on.
SIGINT (Ctrl-C) or SIGTERM stops the experiment: the run going on is dropped, not recorded (a
Gaussian run stops at its next iteration, an interrupted training is never taken for a finished
one), no other run starts, the summary's ``stop_signal`` names the signal, and the same command
resumes with that run.

Outputs (rewritten after every run, so they always show what is done): ``results.csv`` (one row
per run), ``table.md`` (per subject and mean, as the paper's
Table 1, plus the ablation), ``curves.png`` (3D PSNR against seconds, both methods, every subject),
``summary.json``.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from clgs.errors import InputError

METHOD_LABELS = {
    "fdk": "FDK",
    "r2gs": "R2-Gaussian",
    "init": "density init only",
    "init+shape": "+ shape prior",
    "shape": "shape-guided (+ density prior)",
}


def _run_one(method: str, scan, anatomy, iterations: int, seed: int, progress: bool, settings: dict) -> dict:
    """One reconstruction, through :func:`clgs.methods.run.run_method` (the registered method; the
    shape-bound variants are its settings, :data:`SHAPE_VARIANTS`): volume, seconds,
    error-against-time history and, for the methods bound to the shape model, the template surface
    carried by the fitted alpha."""
    from clgs.methods.run import method_accepts, run_method

    t0 = time.perf_counter()
    history, model_surface, jac_min, model_size, model_length, split = [], None, None, None, None, None
    name, variant = EXPERIMENT_METHODS[method]
    chosen = {**settings.get(name, {}), **variant}  # settings are grouped by registered method: "r2gs", "shape"
    if method_accepts(name, "iterations"):
        chosen = {"iterations": iterations, **chosen}
    out = run_method(name, scan, None, chosen, anatomy=anatomy, seed=seed, progress=progress)
    info = out.get("info") or {}
    if info.get("interrupted"):  # a signal stopped the training: not a finished run, never a record
        import signal

        from clgs.cohort.runner import Stopped

        raise Stopped(int(info.get("stop_signal") or signal.SIGINT))
    volume = np.asarray(out["volume"], np.float32)
    res = out.get("result")
    if res is not None:
        history = res.log.rows
    if method in SHAPE_METHODS:
        from clgs.methods.shape_guided import deformed_template_surface

        model_surface = deformed_template_surface(anatomy.template, res.trainer.sets[0])
        if model_surface is not None and anatomy.shape_model is not None:  # the deformation must never fold
            jac_min = float(np.min(anatomy.shape_model.jacobian_determinant(res.trainer.sets[0].alpha.detach())))
        if getattr(res.trainer.sets[0], "fits_size", False):  # the bone's fitted size (the default)
            model_size = res.trainer.sets[0].size
        if getattr(res.trainer.sets[0], "fits_length", False):  # and its length along the leg, where one was fitted
            model_length = res.trainer.sets[0].length
        split = res.displacement  # the surface's displacement: the model's part and the residual's
    seconds = time.perf_counter() - t0
    return {"volume": volume, "seconds": seconds, "history": history,
            "model_surface": model_surface, "jacobian_min": jac_min, "model_size": model_size,
            "model_length": model_length, "displacement": split}


def _made_with(method: str, iterations: int, seed: int, settings: dict, simulation: str = "fine",
               angles=None) -> dict:
    """What a run's result depends on besides the subject, as kept in its record: a resumed experiment
    reuses a record only when these match (else its table would mix runs). Records made before the
    simulation protocol was a choice used ``"same"`` and do not name it; the shape-bound runs name
    whether a size was fitted (``fit_size``: records made before it was fitted count as ``"off"``)
    and a length with it (``fit_length``, ``"off"`` without a fitted size: records made before it
    existed count as ``"off"``), whether a residual deformation was (``residual``, ``"auto"``
    resolved for the views at ``angles``: records made before it existed count as ``"off"``), the
    shape prior's weight (``lambda_shape``: records made before it was named used the paper's 1e-4)
    and the tissue its registration held (``register_tissue``, ``"auto"`` resolved for the views at
    ``angles``, radians: records made before it was named held the free set's start, ``"free"``;
    with the FDK's, the registrations in a row, ``register_passes``: records made before it was
    named made one, and the margin of a later pass's hole, ``pass_hole_margin_mm``: records made
    before it had none), whether the atlas was scaled to the scan (``atlas_calibration``: records
    made before it existed count as ``"off"``) and, with the density prior, whether its tissue was
    carried onto the limb's outline (``limb_outline``: records made before it existed count as
    ``"off"``); every Gaussian run names its schedule (``schedule``:
    records made before schedules existed ran the paper's, compressed to the iterations)."""
    sim = {} if simulation == "same" else {"simulation": simulation}
    if method == "fdk":
        return {"iterations": 0, **sim}
    key = "r2gs" if method == "r2gs" else "shape"
    chosen = {k: v for k, v in settings.get(key, {}).items() if k not in _BOOKKEEPING}
    from clgs.fit.config import GaussianFitConfig

    size = {"schedule": str(chosen.pop("schedule", GaussianFitConfig.schedule))}
    if method in ("init+shape", "shape"):
        from clgs.methods.shape_guided import ShapeGuidedConfig

        size.update(fit_size=str(chosen.pop("fit_size", ShapeGuidedConfig.fit_size)),
                    fit_length=str(chosen.pop("fit_length", ShapeGuidedConfig.fit_length)),
                    residual=str(chosen.pop("residual", ShapeGuidedConfig.residual)),
                    lambda_shape=float(chosen.pop("lambda_shape", ShapeGuidedConfig.lambda_shape)),
                    register_tissue=str(chosen.pop("register_tissue", ShapeGuidedConfig.register_tissue)))
        if size["register_tissue"] == "auto":
            from clgs.methods.shape_guided import registration_tissue

            size["register_tissue"] = "free" if angles is None else registration_tissue("auto", angles)
        if size["residual"] == "auto":
            from clgs.methods.shape_guided import residual_for

            size["residual"] = "off" if angles is None else residual_for("auto", angles)
        if size["fit_size"] != "on":  # a length is a factor of a fitted size: none without one
            size["fit_length"] = "off"
        size["atlas_calibration"] = str(chosen.pop("atlas_calibration", ShapeGuidedConfig.atlas_calibration))
        limb = str(chosen.pop("limb_outline", ShapeGuidedConfig.limb_outline))
        if method == "shape":  # the limb's outline is carried through the density prior only
            size["limb_outline"] = limb
        passes = int(chosen.pop("register_passes", ShapeGuidedConfig.register_passes))
        margin = float(chosen.pop("pass_hole_margin_mm", ShapeGuidedConfig.pass_hole_margin_mm))
        if size["register_tissue"] == "fdk" and passes != 1:  # they repeat the FDK's tissue's registration only
            size.update(register_passes=passes, pass_hole_margin_mm=margin)
    return {"iterations": iterations, "seed": seed,
            "settings": json.loads(json.dumps(chosen, sort_keys=True, default=str)), **sim, **size}


def _tissue_record(meshes, tissue_seed) -> dict:
    """What the scan of a user's surface depends on beyond its file, as its record keeps it: the
    tissue's draw (``tissue_seed``; None: seeded by the surface's name). Nothing for held-out
    subjects, which have their own tissue."""
    return {"tissue_seed": None if tissue_seed is None else int(tissue_seed)} if meshes else {}


def _angles_of(views, angles):
    """The view angles (radians) of an experiment's view set: ``angles`` when given, else the
    count's (``"5"`` or ``"5-fov300"``) spread over a half-turn, as the subject is simulated."""
    if angles is not None:
        return np.asarray(angles, np.float64)
    return np.linspace(0.0, math.pi, int(str(views).split("-fov")[0]), endpoint=False)


# settings that change how often a run logs or saves, not its result
_BOOKKEEPING = {"log_every", "log_early", "checkpoint_every", "checkpoint_dir", "progress"}
_OPTION = {"iterations": "--iterations", "seed": "--seed", "settings": "settings", "detector_fov_mm": "--detector-mm",
           "simulation": "--simulation", "fit_size": "shape-guided setting fit_size",
           "fit_length": "shape-guided setting fit_length",
           "residual": "shape-guided setting residual", "lambda_shape": "shape-guided setting lambda_shape",
           "register_tissue": "shape-guided setting register_tissue",
           "register_passes": "shape-guided setting register_passes",
           "pass_hole_margin_mm": "shape-guided setting pass_hole_margin_mm",
           "atlas_calibration": "shape-guided setting atlas_calibration",
           "limb_outline": "shape-guided setting limb_outline",
           "schedule": "the Gaussian runs' schedule (--set schedule=...)", "tissue_seed": "--tissue-seed"}


def load_experiment_subject(anatomy, sid, meshes, seed: int, tissue_seed: int | None = None):
    """A held-out subject of the anatomy, or with ``meshes`` ({id: (file, units)} or {id: (file,
    units, frame of an untagged file)}) the user's surface ``sid`` made a subject (aligned, its CT
    simulated with a density seeded by its id, or by ``tissue_seed`` when given: every surface then
    gets the same draw of the tissue around it, so that surfaces compare on the same limb)."""
    if not meshes:
        return anatomy.load_subject(sid)
    import zlib

    from clgs.anatomy.simulation import subject_from_mesh_file

    path, units, *space = meshes[sid]
    draw = zlib.crc32(f"{anatomy.name}/{sid}".encode()) if tissue_seed is None else int(tissue_seed)
    return subject_from_mesh_file(anatomy, path, seed=draw, units=units, space=space[0] if space else None)


def _check_same_run(path: Path, row: dict, made_with: dict) -> None:
    """ValueError if the kept record ``row`` was made with other settings than ``made_with``
    (records from before seeds, settings, detectors and simulation protocols were kept count as
    seed 0, no settings, the whole detector and the same-grid protocol)."""
    from clgs.methods.shape_guided import PAPER_LAMBDA_SHAPE

    defaults = {"seed": 0, "settings": {}, "detector_fov_mm": None, "tissue_seed": None, "simulation": "same",
                "fit_size": "off", "fit_length": "off",
                "residual": "off", "schedule": "paper", "lambda_shape": PAPER_LAMBDA_SHAPE,
                "register_tissue": "free", "register_passes": 1, "pass_hole_margin_mm": 0.0,
                "atlas_calibration": "off", "limb_outline": "off"}
    made_with = {"simulation": "same", **made_with}
    for key, want in made_with.items():
        had = row.get(key, defaults.get(key, want))
        if had != want:
            raise InputError(
                f"{path} was made with {key} {had!r}, this run asks for {want!r}: give the same "
                f"{_OPTION[key]} to resume, or another --out folder")


SHAPE_METHODS = ("init", "init+shape", "shape")  # the runs that need the anatomy's model and atlas
# each as settings of the registered shape-guided method (its ablation switches)
SHAPE_VARIANTS = {"init": dict(shape_prior=False, density_prior=False),
                  "init+shape": dict(shape_prior=True, density_prior=False),
                  "shape": dict(shape_prior=True, density_prior=True)}
# the experiment's methods: (registered method, its settings that make the variant)
EXPERIMENT_METHODS = {"fdk": ("fdk", {}), "r2gs": ("r2gs", {}), **{m: ("shape", v) for m, v in SHAPE_VARIANTS.items()}}


def view_plan(views) -> dict:
    """The experiment's view sets by key: a count ``n`` is the papers' set (n views over 180
    degrees, key ``n``, simulated as before); any other spec of :func:`clgs.anatomy.views.view_set`
    (``ap-lat``, ``ap-oblique-lat``, ``carm5``, or degrees ``0,90``) is a clinical set, simulated
    at its own angles (key: its name). Returns {key: radians, or None for a count}."""
    from clgs.anatomy.views import view_set

    plan = {}
    for spec in views:
        if isinstance(spec, (int, np.integer)) or str(spec).strip().isdigit():
            plan[int(spec)] = None
        else:
            vs = view_set(spec)
            plan[vs.key] = vs.radians
    return plan


def run_experiment(anatomy, out_dir, *args, **kwargs) -> dict:
    """:func:`_run_experiment` with ``out_dir`` locked while it runs: a second experiment into the
    same folder is refused naming the first one's process (docs/output-rule.md); finished runs
    there are kept and reused, as ever."""
    from clgs.io.outputs import lock

    with lock(out_dir, "--out"):
        return _run_experiment(anatomy, out_dir, *args, **kwargs)


def _run_experiment(anatomy, out_dir, views=(5, 10), subjects=None, iterations: int = 1000,
                   ablation_views: int | None = 5, methods=("fdk", "r2gs", "shape"), seed: int = 0,
                   progress: bool = True, settings: dict | None = None, echo=print, workers: int | None = None,
                   scheduler: str | None = None, simulation: str = "fine", detector_mm=None, meshes=None,
                   tissue_seed: int | None = None) -> dict:
    """Run (or resume) the experiment; returns the summary dict also written to ``summary.json``.

    ``views``: counts and view sets (:func:`view_plan`); ``detector_mm``: every view set scanned
    twice, whole and with a detector of that field of view (mm at the isocentre, truncated
    projections; see :func:`clgs.anatomy.simulation.scan_geometry`), both judged also inside that
    field of view (``psnr3d_fov``, ``ssim3d_fov``); ``meshes``: {id: (surface file, units)} of the
    user's own subjects instead of the anatomy's held-out ones; ``tissue_seed``: the tissue around
    every one of them drawn from this seed (the same limb for every surface, so that surfaces changed
    from one bone compare on it; None: each surface's own draw, seeded by its id).

    ``simulation``: how the scans are made (:mod:`clgs.ct.simulation_grid`): ``"fine"`` (default,
    projections from a grid twice as fine) or ``"same"`` (R2-Gaussian's same-grid protocol).

    Every run is a task of :func:`clgs.cohort.run_tasks`: here, one after another (``workers``
    None or 0, the default), on a local Dask cluster of ``workers`` processes, or on the running
    cluster at ``scheduler``. A run's record does not depend on where it ran. A run that fails is
    listed with its error under ``failed`` in the summary; the others go on."""
    import signal

    from clgs.cohort import Task, run_tasks
    from clgs.cohort.cluster import check_choice, distributed_wanted
    from clgs.cohort.runner import Stopped, stop_signals
    from clgs.methods.shape_guided import load_anatomy_parts

    check_choice(workers, scheduler)
    out = Path(out_dir)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    settings = dict(settings or {})
    if tissue_seed is not None and not meshes:
        raise InputError("tissue_seed draws the tissue around your own surfaces (meshes); the held-out subjects "
                         "have their own")
    limb = _tissue_record(meshes, tissue_seed)
    if meshes:
        subjects = list(meshes)
    else:
        subjects = list(subjects) if subjects else list(anatomy.test_subjects())
        population = set(anatomy.population()) if anatomy.population else set()
        leaked = population & set(subjects)
        if leaked:
            raise InputError(f"subjects {sorted(leaked)} are in the model's population: evaluate on held-out "
                             "subjects only")
    view_angles = view_plan(views)
    fov = None if detector_mm is None else [float(x) for x in np.broadcast_to(np.asarray(detector_mm, float), (2,))]
    # acquisitions: every view set with the detector that sees the subject whole and, with a
    # detector_mm, again truncated by that detector (key "<set>-fov<mm>"); the whole scan is then
    # also judged inside the truncated one's field of view, so the two compare on the same voxels
    acquisitions = {}
    for v, angles in view_angles.items():
        acquisitions[v] = (angles, None)
        if fov is not None:
            acquisitions[f"{v}-fov{fov[1]:g}"] = (angles, fov)
    views = list(acquisitions)
    plan = []
    for v in views:
        for m in methods:
            plan.append((v, m))
        if ablation_views is not None and v == ablation_views:
            plan += [(v, "init"), (v, "init+shape")]
    remote = distributed_wanted(workers, scheduler)
    if any(m in SHAPE_METHODS for _, m in plan):
        # builds a missing model here, once, before any run needs it (runs in this process share it)
        parts = load_anatomy_parts(anatomy)
        if not remote:
            _CACHE["parts"] = (("parts", anatomy.name, str(anatomy.model_path)), parts)
    where = anatomy_by_name(anatomy) if remote else anatomy
    order, done, tasks = [], {}, []
    for sid in subjects:
        for v in list(dict.fromkeys(p[0] for p in plan)):
            angles, det = acquisitions[v]
            for vv, method in plan:
                if vv != v:
                    continue
                tag = f"{sid}_{v}_{method.replace('+', '-')}"
                order.append(tag)
                record_path = out / "runs" / f"{tag}.json"
                made_with = dict(_made_with(method, iterations, seed, settings, simulation,
                                            _angles_of(v, angles)), detector_fov_mm=det, **limb)
                if record_path.is_file():
                    row = json.loads(record_path.read_text())
                    _check_same_run(record_path, row, made_with)
                    outdated = surface_outdated(anatomy, row)
                    if outdated and (out / "runs" / f"{tag}.nii.gz").is_file():
                        row = remeasure_surface(anatomy, row, out, tag, angles, det, seed, simulation, meshes,
                                                tissue_seed)
                        mm = row.get("surface_mean_mm", float("nan"))
                        echo(f"{tag}: done before, kept; its bone surface taken again from its volume "
                             f"(gaps in the wall sealed as the anatomy asks): {mm:.2f} mm")
                    elif outdated:
                        echo(f"{tag}: done before, kept, but its bone surface was taken without the closing "
                             f"the anatomy now asks for and runs/{tag}.nii.gz is gone: its surface figures "
                             "are not comparable with the others (delete its record to run it again)")
                    else:
                        echo(f"{tag}: done before, kept")
                    done[tag] = row
                    continue
                tasks.append(Task(tag, run_and_record, kwargs=dict(
                    anatomy=where, subject_id=sid, views=v, method=method, iterations=iterations, seed=seed,
                    settings=settings, out_dir=str(out), progress=progress and not remote,
                    echo=None if remote else echo, simulation=simulation,
                    angles=None if angles is None else [float(a) for a in angles], detector_mm=det,
                    judge_fov=fov if det is None else None, meshes=meshes, tissue_seed=tissue_seed)))
    failed: dict = {}

    def finished(outcome):
        if outcome.ok:
            row = done[outcome.key] = outcome.result
            psnr, ssim = row.get("psnr3d", float("nan")), row.get("ssim3d", float("nan"))
            echo(f"  {outcome.key}: PSNR {psnr:.2f} dB, SSIM {ssim:.4f}, "
                 f"surface {row.get('surface_mean_mm', float('nan')):.2f} mm, {row['seconds']:.0f} s")
        else:
            failed[outcome.key] = outcome.error
            echo(f"  {outcome.key}: FAILED: {outcome.error}")
        rows = [done[t] for t in order if t in done]
        write_reports(out, rows, summarise(rows, views, ablation_views, failed), views, ablation_views)

    with stop_signals() as stop:
        try:
            run_tasks(tasks, workers=workers, scheduler=scheduler, on_outcome=finished, desc="experiment runs",
                      progress=remote or not progress, echo=echo, stop=stop)
        except Stopped as exc:  # the run going on is dropped (runs here keep no checkpoint)
            stop.request(exc.signum)
            for key in exc.running:
                echo(f"  {key}: stopped by {signal.Signals(exc.signum).name}; not recorded, it runs again on resume")
    rows = [done[t] for t in order if t in done]
    summary = summarise(rows, views, ablation_views, failed)
    if stop.signum is not None:  # what stopped the experiment
        summary["stop_signal"] = int(stop.signum)
    write_reports(out, rows, summary, views, ablation_views)
    return summary


def anatomy_by_name(anatomy) -> str:
    """The name under which worker processes find ``anatomy`` (an installed plugin): they load it,
    its model and its subjects themselves instead of receiving them pickled."""
    from clgs.anatomy import plugins

    try:
        plugins.get_anatomy(anatomy.name)
    except LookupError as exc:
        raise InputError(f"the {anatomy.name!r} anatomy is not an installed plugin, so worker processes cannot "
                         f"load it: install its package, or run without --workers/--scheduler ({exc})") from exc
    return anatomy.name


# the latest scan and model of this process (kind -> (key, value)): consecutive runs of one
# subject and view count simulate its scan once, as the experiment's loop did before it had tasks
_CACHE: dict = {}


def _cached(key, make):
    kind = key[0]
    if _CACHE.get(kind, (None,))[0] != key:
        _CACHE.pop(kind, None)  # let the old one go before the new one is made
        _CACHE[kind] = (key, make())
    return _CACHE[kind][1]


def _experiment_scan(anatomy, subject_id, n, angles, detector_mm, seed, simulation, meshes, tissue_seed) -> tuple:
    """(subject, scan) of one experiment run, made once per process (runs of one scan share it)."""
    from clgs.anatomy.simulation import simulate_subject

    det_key = None if detector_mm is None else tuple(detector_mm)
    ang_key = None if angles is None else tuple(angles)
    subject = _cached(("subject", anatomy.name, subject_id, bool(meshes), tissue_seed),
                      lambda: load_experiment_subject(anatomy, subject_id, meshes, seed, tissue_seed))
    scan = _cached(("scan", anatomy.name, subject_id, n, ang_key, det_key, seed, simulation, tissue_seed),
                   lambda: simulate_subject(
        anatomy, subject, n, math.pi, True, seed, protocol=simulation, angles=angles, detector_mm=detector_mm))
    return subject, scan


def surface_outdated(anatomy, row: dict) -> bool:
    """Whether a kept record's bone surface was taken with another closing than the anatomy's
    today (records made before surfaces sealed gaps in the bone's wall name none: 0)."""
    from clgs.anatomy.bone_level import anatomy_closing

    if row.get("surface_level") is None:
        return False
    return int(row.get("surface_closing_max_voxels", 0)) != anatomy_closing(anatomy)


def _measured_surface(anatomy, scan, volume) -> tuple:
    """(mesh or None, level, metrics) of a run's volume: the outer bone surface at the level the
    anatomy and scan give, and :func:`clgs.anatomy.evaluation.evaluate_volume`'s figures of that
    same mesh (with the closing radius used, where the anatomy seals holes in the wall)."""
    from clgs.anatomy.bone_level import choose_level
    from clgs.anatomy.evaluation import bone_surface_closed, evaluate_volume

    level = choose_level(anatomy=anatomy, truth=scan.truth, scan_meta=scan.meta)
    found = None if level is None else bone_surface_closed(volume, scan.geometry, level)
    mesh = None if found is None else found[0]
    metrics = evaluate_volume(anatomy, scan, volume, surface=mesh, level=level)
    if found is not None and level.closing:
        metrics["surface_closing_voxels"] = found[1]
    return mesh, level, metrics


def remeasure_surface(anatomy, row: dict, out_dir, tag: str, angles=None, detector_mm=None, seed: int = 0,
                      simulation: str = "fine", meshes=None, tissue_seed=None) -> dict:
    """A kept record with its bone surface taken again from its saved volume (``runs/<tag>.nii.gz``)
    as a run makes it today: the mesh, the picture and the surface figures replaced, the rest kept.
    So a resumed experiment's table never mixes surfaces taken two ways, and no run is repeated."""
    from clgs.anatomy.surface_figure import reconstruction_figure
    from clgs.io import atomic
    from clgs.io.mesh import load_mesh, save_mesh
    from clgs.io.volume import load_volume

    runs = Path(out_dir) / "runs"
    v = row["views"]
    n = int(str(v).split("-fov")[0]) if angles is None else len(angles)
    _, scan = _experiment_scan(anatomy, row["subject"], n, angles, detector_mm, seed, simulation, meshes, tissue_seed)
    volume = load_volume(runs / f"{tag}.nii.gz").volume
    mesh, level, metrics = _measured_surface(anatomy, scan, volume)
    row = {k: x for k, x in row.items() if not (k.startswith("surface_") and not k.startswith("surface_file"))}
    row.update({k: x for k, x in metrics.items() if k.startswith("surface_")})
    (runs / f"{tag}.stl").unlink(missing_ok=True)
    row["surface_file"] = None if mesh is None else str(save_mesh(runs / f"{tag}.stl", mesh.vertices, mesh.faces))
    model = runs / f"{tag}_model.stl"
    model_surface = tuple(load_mesh(model)) if model.is_file() else None
    reconstruction_figure(runs / f"{tag}_surface.png", anatomy, scan, volume, model_surface, mesh=mesh, level=level,
                          title=f"{row['subject']}, {views_label(v)}, {METHOD_LABELS[row['method']]}")
    atomic.write_json(runs / f"{tag}.json", row)
    return row


def run_and_record(anatomy, subject_id, views, method, iterations, seed, settings, out_dir, progress=False,
                   echo=None, simulation: str = "fine", angles=None, detector_mm=None, judge_fov=None,
                   meshes=None, tissue_seed: int | None = None) -> dict:
    """One run of the experiment, start to finish, wherever it runs: simulate the subject's scan
    (seeded: the same everywhere), reconstruct, score, write the volume, the surfaces, the surface
    picture and the record ``runs/<tag>.json`` (atomically, last); returns the record. ``anatomy``
    is an :class:`clgs.anatomy.Anatomy` or the name of an installed one (worker processes).
    ``views`` is a view count or a view-set key (then ``angles``, radians, are its views);
    ``detector_mm``: a truncating detector; ``judge_fov``: also score inside that detector's field
    of view (the untruncated twin of a truncated scan); ``meshes``: the user's own subjects."""
    from clgs.anatomy.simulation import scan_geometry
    from clgs.anatomy.surface_figure import reconstruction_figure
    from clgs.io import atomic
    from clgs.io.mesh import save_mesh
    from clgs.io.volume import save_volume
    from clgs.methods.shape_guided import load_anatomy_parts
    from clgs.metrics import surface_distance

    if isinstance(anatomy, str):
        from clgs.anatomy import plugins

        anatomy = plugins.get_anatomy(anatomy)
    out = Path(out_dir)
    v = views if isinstance(views, str) and not views.isdigit() else int(views)
    # a count's key may carry a truncating detector ("5-fov300"): its views are the count's
    n = int(str(v).split("-fov")[0]) if angles is None else len(angles)
    tag = f"{subject_id}_{v}_{method.replace('+', '-')}"
    if echo is not None:
        echo(f"{tag}: reconstructing ({METHOD_LABELS[method]}, {views_label(v)})")
    subject, scan = _experiment_scan(anatomy, subject_id, n, angles, detector_mm, seed, simulation, meshes,
                                     tissue_seed)
    parts = None
    if method in SHAPE_METHODS:
        parts = _cached(("parts", anatomy.name, str(anatomy.model_path)), lambda: load_anatomy_parts(anatomy))
    made_with = dict(_made_with(method, iterations, seed, settings, simulation, scan.geometry.angles),
                     detector_fov_mm=None if detector_mm is None else [float(x) for x in detector_mm],
                     **_tissue_record(meshes, tissue_seed))
    run = _run_one(method, scan, parts, iterations, seed, progress, settings)
    # the surface scored is the surface written: one mesh, at one level (named in the record)
    mesh, level, metrics = _measured_surface(anatomy, scan, run["volume"])
    if judge_fov is not None and metrics.get("psnr3d") is not None:
        judge = scan_geometry(anatomy, subject, n, math.pi, angles=angles, detector_mm=judge_fov).field_of_view()
        if judge.any():
            from clgs import metrics as figures

            metrics.update(psnr3d_fov=float(figures.masked_psnr3d(run["volume"], scan.truth, judge)),
                           ssim3d_fov=float(figures.masked_ssim3d(run["volume"], scan.truth, judge)),
                           fov_fraction=float(judge.mean()))
    save_volume(out / "runs" / f"{tag}.nii.gz", run["volume"], scan.geometry, units="1/mm")
    surf = None if mesh is None else save_mesh(out / "runs" / f"{tag}.stl", mesh.vertices, mesh.faces)
    if run["model_surface"] is not None and scan.surface is not None:
        # the shape model's own bone surface: the template moved by the fitted alpha
        sd = surface_distance(run["model_surface"], scan.surface)
        metrics.update({f"model_surface_{k}_mm": x for k, x in sd.items()})
        save_mesh(out / "runs" / f"{tag}_model.stl", *run["model_surface"])
    reconstruction_figure(out / "runs" / f"{tag}_surface.png", anatomy, scan, run["volume"], run["model_surface"],
                          mesh=mesh, level=level, title=f"{subject_id}, {views_label(v)}, {METHOD_LABELS[method]}")
    row = {"subject": subject_id, "views": v, "method": method, "seconds": run["seconds"], **made_with,
           "angles_deg": [round(math.degrees(a), 6) for a in scan.geometry.angles],
           "jacobian_min": run["jacobian_min"], "model_size": run.get("model_size"),
           "model_length": run.get("model_length"),
           "displacement": run.get("displacement"),
           **{k: (float(x) if isinstance(x, (int, float, np.floating)) else x) for k, x in metrics.items()},
           "surface_file": None if surf is None else str(surf),
           "history": [{k: r.get(k) for k in ("iteration", "seconds", "psnr3d", "ssim3d")}
                       for r in run["history"]]}
    atomic.write_json(out / "runs" / f"{tag}.json", row)
    return row


def summarise(rows, views, ablation_views, failed=None) -> dict:
    """Mean PSNR / SSIM / surface distance / seconds per (views, method), the gains, and the runs
    that failed (``failed``: run tag -> error)."""
    out = {"per_method": {}, "gain_db": {}, "failed": dict(sorted((failed or {}).items()))}
    for v in views:
        for m in sorted({r["method"] for r in rows if r["views"] == v}):
            sel = [r for r in rows if r["views"] == v and r["method"] == m]
            out["per_method"][f"{v}/{m}"] = {
                k: float(np.mean([r[k] for r in sel if r.get(k) is not None]))
                for k in ("psnr3d", "ssim3d", "psnr3d_fov", "ssim3d_fov", "surface_mean_mm", "surface_p95_mm",
                          "surface_hausdorff_mm",
                          "model_surface_mean_mm", "model_surface_p95_mm", "model_surface_hausdorff_mm", "seconds")
                if any(r.get(k) is not None for r in sel)}
            jac = [r["jacobian_min"] for r in sel if r.get("jacobian_min") is not None]
            if jac:  # the worst subject: the deformation must never fold (> 0)
                out["per_method"][f"{v}/{m}"]["jacobian_min"] = float(np.min(jac))
        a = {r["subject"]: r["psnr3d"] for r in rows if r["views"] == v and r["method"] == "shape"}
        b = {r["subject"]: r["psnr3d"] for r in rows if r["views"] == v and r["method"] == "r2gs"}
        common = sorted(set(a) & set(b))
        if common:
            gains = [a[s] - b[s] for s in common]
            out["gain_db"][str(v)] = {"mean": float(np.mean(gains)), "min": float(np.min(gains)),
                                      "subjects_ahead": int(sum(g > 0 for g in gains)), "subjects": len(common)}
    return out


def _per_subject_range(rows, key: str) -> str:
    """"subject min[-max], ..." of a figure the rows hold (None where none holds it), over each
    subject's runs."""
    per: dict = {}
    for r in rows:
        if r.get(key) is not None:
            per.setdefault(r["subject"], []).append(float(r[key]))
    return ", ".join(f"{s} {min(v):.3f}" + (f"-{max(v):.3f}" if max(v) > min(v) else "")
                     for s, v in sorted(per.items()))


def write_reports(out: Path, rows, summary, views, ablation_views) -> None:
    from clgs.io import atomic

    keys = ["subject", "views", "method", "psnr3d", "ssim3d", "psnr3d_fov", "ssim3d_fov", "surface_mean_mm",
            "surface_p95_mm",
            "surface_hausdorff_mm", "model_surface_mean_mm", "model_surface_p95_mm", "model_surface_hausdorff_mm",
            "jacobian_min", "model_size", "model_length", "seconds", "iterations", "schedule", "detector_fov_mm"]
    def cell(x):
        return "" if x is None else ("x".join(f"{v:g}" for v in x) if isinstance(x, list) else str(x))

    lines = [",".join(keys)] + [",".join(cell(r.get(k)) for k in keys) for r in rows]
    atomic.write_text(out / "results.csv", "\n".join(lines) + "\n")
    atomic.write_text(out / "table.md", markdown_tables(rows, summary, views, ablation_views))
    atomic.write_json(out / "summary.json", summary)
    plot_curves(out / "curves.png", rows, views)


def views_label(v) -> str:
    """'5 views' for a count over 180 degrees; a clinical set by its name and angles."""
    if isinstance(v, (int, np.integer)) or str(v).isdigit():
        return f"{v} views"
    if "-fov" in str(v):
        base, mm = str(v).rsplit("-fov", 1)
        return f"{views_label(int(base) if base.isdigit() else base)}, {mm} mm detector"
    from clgs.anatomy.views import view_set

    vs = view_set(v) if not str(v).startswith("deg") else None
    return f"{v} ({', '.join(f'{d:g}' for d in vs.degrees)} deg)" if vs is not None else str(v)


def markdown_tables(rows, summary, views, ablation_views) -> str:
    def fmt(x, d=2):
        return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{d}f}"

    subjects = sorted({r["subject"] for r in rows})
    text = ["## 3D PSNR (dB) / SSIM per held-out subject", ""]
    methods = [m for m in ("fdk", "r2gs", "shape") if any(r["method"] == m for r in rows)]
    head = "| subject | " + " | ".join(f"{METHOD_LABELS[m]} {views_label(v)}" for v in views for m in methods) + " |"
    text += [head, "|" + "---|" * (1 + len(views) * len(methods))]
    for s in subjects + ["mean"]:
        cells = []
        for v in views:
            for m in methods:
                if s == "mean":
                    pm = summary["per_method"].get(f"{v}/{m}", {})
                    cells.append(f"**{fmt(pm.get('psnr3d'))} / {fmt(pm.get('ssim3d'), 3)}**")
                else:
                    r = next((r for r in rows if r["subject"] == s and r["views"] == v and r["method"] == m), None)
                    cells.append("-" if r is None else f"{fmt(r.get('psnr3d'))} / {fmt(r.get('ssim3d'), 3)}")
        text.append(f"| {s} | " + " | ".join(cells) + " |")
    text += ["", "## Mean surface distance (mm) and run time (s)", "",
             "Volume surface: the outer bone surface of the reconstructed volume. Model surface: the "
             "template carried by the fitted shape coefficients (shape-guided only).", "",
             "| views | method | volume surface mean / p95 / Hausdorff | model surface mean / p95 / Hausdorff | "
             "min det J | seconds |",
             "|---|---|---|---|---|---|"]
    for v in views:
        for m in methods:
            pm = summary["per_method"].get(f"{v}/{m}", {})
            text.append(f"| {views_label(v)} | {METHOD_LABELS[m]} | {fmt(pm.get('surface_mean_mm'))} / "
                        f"{fmt(pm.get('surface_p95_mm'))} / {fmt(pm.get('surface_hausdorff_mm'))} | "
                        f"{fmt(pm.get('model_surface_mean_mm'))} / {fmt(pm.get('model_surface_p95_mm'))} / "
                        f"{fmt(pm.get('model_surface_hausdorff_mm'))} | {fmt(pm.get('jacobian_min'), 3)} | "
                        f"{fmt(pm.get('seconds'), 0)} |")
    # the bone's fitted size (clgs.shape.size) and, where one was fitted, its length along the leg
    # (fit_length), per subject over its view sets
    for key, title in (("model_size", "Fitted bone size, times the shape model's (per subject, over its runs)"),
                       ("model_length", "Fitted bone length along the leg, times its size (where one was fitted)")):
        ranges = _per_subject_range(rows, key)
        if ranges:
            text += ["", f"{title}: {ranges}"]
    if any(r.get("psnr3d_fov") is not None for r in rows):
        text += ["", "## Inside the detector's field of view (truncated scans)", "",
                 "3D PSNR / SSIM over the voxels every view measured whole (the rest of the bone was "
                 "outside the detector in some views).", "", "| views | method | 3D PSNR / SSIM in the field of view |",
                 "|---|---|---|"]
        for v in views:
            for m in methods:
                pm = summary["per_method"].get(f"{v}/{m}", {})
                if pm.get("psnr3d_fov") is not None:
                    text.append(f"| {views_label(v)} | {METHOD_LABELS[m]} | {fmt(pm.get('psnr3d_fov'))} / "
                                f"{fmt(pm.get('ssim3d_fov'), 3)} |")
    if summary["gain_db"]:
        text += ["", "Shape-guided minus R2-Gaussian, 3D PSNR (dB): " + "; ".join(
            f"{views_label(v)}: mean {g['mean']:+.2f}, worst {g['min']:+.2f}, ahead on "
            f"{g['subjects_ahead']}/{g['subjects']}"
            for v, g in summary["gain_db"].items())]
    if summary.get("failed"):
        text += ["", "## Failed runs", "", "| run | error |", "|---|---|"]
        text += [f"| {tag} | {err.replace('|', '/')} |" for tag, err in summary["failed"].items()]
    if ablation_views is not None and any(f"{ablation_views}/{m}" in summary["per_method"]
                                          for m in ("init", "init+shape")):
        text += ["", f"## Ablation at {ablation_views} views (mean over subjects)", "",
                 "| variant | 3D PSNR | 3D SSIM | surface mean (mm) | seconds |", "|---|---|---|---|---|"]
        for m in ("init", "init+shape", "shape"):
            pm = summary["per_method"].get(f"{ablation_views}/{m}")
            if pm:
                text.append(f"| {METHOD_LABELS[m]} | {fmt(pm.get('psnr3d'))} | {fmt(pm.get('ssim3d'), 3)} | "
                            f"{fmt(pm.get('surface_mean_mm'))} | {fmt(pm.get('seconds'), 0)} |")
    return "\n".join(text) + "\n"


def plot_curves(path, rows, views) -> None:
    """3D PSNR against training seconds: R2-Gaussian and shape-guided, one line per subject."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from clgs.io import atomic

    fig, axes = plt.subplots(1, len(views), figsize=(5.5 * len(views), 4), squeeze=False)
    colours = {"r2gs": "tab:blue", "shape": "tab:red", "init": "tab:gray", "init+shape": "tab:orange"}
    for ax, v in zip(axes[0], views):
        for r in rows:
            if r["views"] != v:
                continue
            if r["method"] == "fdk":  # no curve: one point at its (sub-second) run time
                ax.plot([r["seconds"]], [r["psnr3d"]], "s", color="tab:green", alpha=0.7, label=METHOD_LABELS["fdk"])
                continue
            h = [x for x in r.get("history") or [] if x.get("psnr3d") is not None]
            if h:
                ax.plot([x["seconds"] for x in h], [x["psnr3d"] for x in h], color=colours.get(r["method"], "k"),
                        alpha=0.7, label=METHOD_LABELS[r["method"]])
        handles, labels = ax.get_legend_handles_labels()
        uniq = dict(zip(labels, handles))
        ax.legend(uniq.values(), uniq.keys(), fontsize=8)
        ax.set_xlabel("training time (s)")
        ax.set_ylabel("3D PSNR (dB)")
        ax.set_title(views_label(v))
        ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
