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

import json
import os
import time

import click

_GEOMETRY_KEYS = ("mode", "DSO", "DSD", "nDetector", "dDetector", "offDetector")


def _need(anatomy, attr, what):
    fn = getattr(anatomy, attr, None)
    if fn is None:
        raise click.ClickException(f"the {anatomy.name} plugin ({anatomy.package or 'unknown package'}) provides no "
                                   f"{attr}: cannot {what}")
    return fn


def _array(x):
    import numpy as np

    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, np.float32)


# --------------------------------------------------------------------------------------- library
def scan_geometry(anatomy, subject, n_views: int, arc: float):
    """The anatomy's default scanner (``scene``) around the subject's CT grid.

    The volume grid is the subject's own (nVoxel, dVoxel, and offOrigin = its centre); source,
    detector and mode come from ``anatomy.scene`` (TIGRE names), or are sized to see the volume
    whole (DSD/DSO = 1500/1000 mm) when the plugin gives none."""
    import numpy as np

    from clgs.geometry import Geometry

    shape = np.asarray(subject.volume.shape)
    spacing = np.asarray(subject.spacing, float)
    centre = np.asarray(subject.origin, float) + 0.5 * (shape - 1) * spacing
    angles = np.linspace(0.0, arc, int(n_views), endpoint=False)
    scene = dict(anatomy.scene or {})
    d = {k: scene[k] for k in _GEOMETRY_KEYS if k in scene}
    d.update(nVoxel=tuple(int(s) for s in shape), dVoxel=tuple(spacing), offOrigin=tuple(centre), angles=angles)
    if "nDetector" not in d or "dDetector" not in d:
        size = float((shape * spacing).max())
        d.setdefault("DSO", 1000.0)
        d.setdefault("DSD", 1500.0)
        mag = d["DSD"] / d["DSO"] if d.get("mode", "cone") == "cone" else 1.0
        half = 0.5 * size * np.sqrt(2.0) * mag * 1.05 + np.linalg.norm(centre[1:]) * mag
        n_det = int(scene.get("n_detector", 256))
        d.update(nDetector=(n_det, n_det), dDetector=(2 * half / n_det,) * 2)
    d.setdefault("DSO", 1000.0)
    d.setdefault("DSD", 1500.0)
    return Geometry(**d)


def subject_from_mesh_file(anatomy, path, seed: int = 0):
    """A Subject (with a CT volume) from a surface file: the plugin's ``subject_from_mesh`` when it
    has one; otherwise the surface filled with a uniform bone attenuation ``scene['density']``
    (1/mm, default 0.04) on a grid of the template's spacing with a 10 mm margin."""
    if getattr(anatomy, "subject_from_mesh", None) is not None:
        out = anatomy.subject_from_mesh(path, seed=seed)
        return out[0] if isinstance(out, tuple) else out
    import numpy as np

    from clgs.io.mesh import load_mesh
    from clgs.template import Subject, box_grid, mesh_to_label

    v, f = load_mesh(path)
    v = np.asarray(v, float)
    spacing = float(min(anatomy.load_template().spacing)) if anatomy.load_template is not None else 2.0
    shape, sp, org = box_grid(v.min(0) - 10.0, v.max(0) + 10.0, spacing=spacing)
    density = float((anatomy.scene or {}).get("density", 0.04))
    vol = mesh_to_label(v, f, shape, sp, org).astype(np.float32) * density
    sid = os.path.splitext(os.path.basename(os.fspath(path)))[0]
    return Subject(sid, v, f, volume=vol, spacing=sp, origin=org,
                   meta={"source": os.path.abspath(os.fspath(path)), "density_model": "uniform", "density": density})


def simulate_subject(anatomy, subject, n_views: int = 50, arc: float = 3.141592653589793, noise: bool = True,
                     seed: int = 0, noise_options: dict = None):
    """Project a subject's CT with the anatomy's scanner, add noise: a :class:`clgs.io.scan.Scan`.

    The truth volume and the true surface travel with the scan (for evaluation)."""
    from clgs.ct.projector import CTProjector
    from clgs.io.scan import Scan

    if subject.volume is None:
        raise click.ClickException(f"subject {subject.id} has no CT volume to simulate")
    geo = scan_geometry(anatomy, subject, n_views, arc)
    proj = _array(CTProjector(geo).forward(subject.volume))
    acquisition = {"noise": bool(noise), "seed": int(seed)}
    if noise:
        from clgs.ct.noise import add_noise

        opts = dict(noise_options or {})
        proj = _array(add_noise(proj, seed=seed, **opts))
        acquisition.update(opts)
    meta = {"anatomy": anatomy.name, "subject": subject.id, "acquisition": acquisition,
            "provenance": f"clgs {anatomy.name} simulate ({anatomy.package or 'plugin'} {anatomy.version})",
            "subject_meta": subject.meta}
    return Scan(geo, proj, truth=subject.volume, meta=meta, surface=(subject.vertices, subject.faces))


def default_method(anatomy) -> str:
    return "shape" if anatomy.load_shape_model is not None else "r2gs"


def method_accepts(method: str, option: str) -> bool:
    """Whether the registered method's callable takes ``option`` (False when unknown)."""
    import inspect

    try:
        from clgs import methods

        params = inspect.signature(methods.get(method).callable()).parameters
    except Exception:  # noqa: BLE001 - unknown or unimportable: the run reports it properly
        return False
    return option in params or any(p.kind == p.VAR_KEYWORD for p in params.values())


def run_reconstruct(scan, anatomy, method: str, out=None, **options):
    """Reconstruct through ``clgs.recon.reconstruct`` when it exists, else the method registry
    (:mod:`clgs.methods`); the anatomy is passed to methods that take it. Returns the method's
    result dict (at least ``volume``)."""
    import importlib
    import inspect

    try:
        recon = importlib.import_module("clgs.recon")
    except ImportError:
        recon = None
    if recon is not None and hasattr(recon, "reconstruct"):
        return recon.reconstruct(scan, anatomy=anatomy, method=method, out=out, **options)
    try:
        from clgs import methods
    except ImportError:
        methods = None
    if methods is None:
        raise click.ClickException(f"reconstruction method {method!r} is not available in this clgs")
    try:
        m = methods.get(method)
    except LookupError as exc:
        raise click.ClickException(f"reconstruction method {method!r} is not available: {exc}")
    run = m.callable()
    params = inspect.signature(run).parameters
    takes_any = any(p.kind == p.VAR_KEYWORD for p in params.values())
    if "anatomy" in params or takes_any:
        options["anatomy"] = anatomy
    result = run(scan, out, **options)
    if out is not None and "volume" in result:
        from clgs.io.volume import save_volume

        os.makedirs(out, exist_ok=True)
        target = os.path.join(out, "volume.npy")
        if not os.path.exists(target):
            save_volume(target, _array(result["volume"]), scan.geometry)
    return result


def surface_level(anatomy, truth) -> float:
    """The bone iso-level: ``scene['surface_level']`` or the upper of 3-class Otsu thresholds."""
    level = (anatomy.scene or {}).get("surface_level")
    if level is not None:
        return float(level)
    import numpy as np
    from skimage.filters import threshold_multiotsu

    t = np.asarray(truth, np.float32)
    return float(threshold_multiotsu(t[:: max(1, t.shape[0] // 64)], classes=3)[-1])


def bone_mask(volume, level: float):
    """The solid bone: voxels above ``level``, enclosed cavities (medullary canal, cancellous
    interior below the level) filled, only the largest connected piece kept; so the surface
    compared is the outer bone surface, not every iso-contour."""
    import numpy as np
    from scipy import ndimage

    mask = np.asarray(volume) > level
    labels, n = ndimage.label(mask)
    if n > 1:
        sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, n + 1))
        mask = labels == (1 + int(np.argmax(sizes)))
    return ndimage.binary_fill_holes(mask)


def evaluate_volume(anatomy, scan, volume) -> dict:
    """PSNR/SSIM against the scan's truth and, when the scan has the true surface, the surface
    distance (mm) from the reconstruction's outer bone surface (:func:`bone_mask`) to it."""
    import numpy as np

    from clgs import metrics

    if scan.truth is None:
        raise click.ClickException("the scan has no truth volume to evaluate against (only simulated scans have one)")
    vol = _array(volume)
    if vol.shape != scan.truth.shape:
        raise click.ClickException(f"reconstruction {vol.shape} and truth {scan.truth.shape} differ in shape")
    out = metrics.evaluate_volume(vol, scan.truth)
    if scan.surface is not None:
        from clgs.surface import SurfaceError, surface_from_volume

        level = surface_level(anatomy, scan.truth)
        try:
            mesh = surface_from_volume(bone_mask(vol, level), geometry=scan.geometry)
            sd = metrics.surface_distance(mesh, scan.surface, n_samples=20000)
            out.update({f"surface_{k}_mm": v for k, v in sd.items()}, surface_level=level)
        except SurfaceError as exc:
            out["surface_error"] = str(exc)
    return out


def _echo_metrics(m: dict):
    for k, v in m.items():
        if isinstance(v, float):
            click.echo(f"  {k:22s} {v:.4f}")
        elif isinstance(v, (list, tuple)):
            click.echo(f"  {k:22s} " + " ".join(f"{x:.4f}" for x in v))
        else:
            click.echo(f"  {k:22s} {v}")


def _parse_options(pairs):
    opts = {}
    for p in pairs:
        if "=" not in p:
            raise click.BadParameter(f"expected KEY=VALUE, got {p!r}", param_hint="--set")
        k, v = p.split("=", 1)
        try:
            opts[k.replace("-", "_")] = json.loads(v)
        except json.JSONDecodeError:
            opts[k.replace("-", "_")] = v
    return opts


# --------------------------------------------------------------------------------------- group
def make_group(anatomy) -> click.Group:
    """The click group ``clgs <anatomy.name>`` with the generic commands and the plugin's own."""
    name = anatomy.name
    scene = anatomy.scene or {}

    @click.group(name=name, help=f"{anatomy.summary}\n\nPlugin: {anatomy.package or '?'} {anatomy.version}.")
    def group():
        pass

    @group.command()
    @click.option("--subject", "subject_id", help="subject id (held-out ones: see `info`)")
    @click.option("--mesh", type=click.Path(exists=True, dir_okay=False), help="a surface file (mm) instead")
    @click.option("--out", required=True, type=click.Path(file_okay=False), help="scan folder to write")
    @click.option("--views", default=int(scene.get("n_views", 50)), show_default=True, help="number of projections")
    @click.option("--arc", default=float(scene.get("arc_deg", 180.0)), show_default=True, help="arc in degrees")
    @click.option("--noise/--no-noise", default=True, show_default=True, help="Poisson + electronic noise")
    @click.option("--seed", default=0, show_default=True)
    @click.option("--overwrite", is_flag=True, help="replace an existing scan folder")
    def simulate(subject_id, mesh, out, views, arc, noise, seed, overwrite):
        """Simulate a CT scan of a subject (default: the first held-out one) or of a surface file."""
        import math

        if subject_id and mesh:
            raise click.UsageError("give --subject or --mesh, not both")
        if mesh:
            subject = subject_from_mesh_file(anatomy, mesh, seed=seed)
        else:
            if not subject_id:
                held = _need(anatomy, "test_subjects", "pick a held-out subject")()
                if not held:
                    raise click.UsageError("the plugin has no held-out subjects: give --subject or --mesh")
                subject_id = held[0]
            subject = _need(anatomy, "load_subject", "load a subject")(subject_id)
        scan = simulate_subject(anatomy, subject, views, math.radians(arc), noise, seed)
        try:
            scan.save(out, overwrite=overwrite)
        except FileExistsError:
            raise click.ClickException(f"{out} exists: pass --overwrite to replace it")
        click.echo(f"{name}: subject {subject.id} -> {out} ({views} views over {arc:g} deg, "
                   f"{'noisy' if noise else 'noiseless'})")

    @group.command()
    @click.argument("scan_dir", type=click.Path(exists=True, file_okay=False))
    @click.option("--out", required=True, type=click.Path(file_okay=False), help="output folder")
    @click.option("--method", default=None, help="shape (default with a shape model) | r2gs | fdk | sart | ...")
    @click.option("--views", default=None, type=int, help="use only this many views, evenly spread")
    @click.option("--set", "settings", multiple=True, metavar="KEY=VALUE", help="method option (repeatable)")
    def reconstruct(scan_dir, out, method, views, settings):
        """Reconstruct a scan folder with the anatomy's prior; writes OUT/volume.npy."""
        from clgs.io.scan import Scan

        scan = Scan.load(scan_dir)
        if views:
            import numpy as np

            scan = scan.subset(np.linspace(0, scan.n_views, views, endpoint=False).astype(int))
        method = method or default_method(anatomy)
        t0 = time.perf_counter()
        result = run_reconstruct(scan, anatomy, method, out=out, **_parse_options(settings))
        click.echo(f"{name}: {method} reconstruction of {scan.n_views} views in {time.perf_counter() - t0:.1f} s -> {out}")
        if scan.truth is not None and "volume" in result:
            _echo_metrics(evaluate_volume(anatomy, scan, result["volume"]))

    @group.command("build-model")
    @click.option("--out", "out_path", type=click.Path(dir_okay=False), help="model file (default: the plugin's)")
    @click.option("--variance", type=float, default=None, help="fraction of variance to keep [0.95]")
    @click.option("--n-modes", type=int, default=None, help="keep exactly this many modes")
    @click.option("--max-cells", type=int, default=None, help="velocity grid cells along the longest side")
    @click.option("--force", is_flag=True, help="rebuild even if an up-to-date model exists")
    def build_model_cmd(out_path, variance, n_modes, max_cells, force):
        """Register the population to the template, PCA of the velocities, density atlas."""
        settings = {k: v for k, v in dict(variance=variance, n_modes=n_modes, max_cells=max_cells).items()
                    if v is not None}
        t0 = time.perf_counter()
        if anatomy.build_model is not None:
            kwargs = dict(settings, force=force)
            if out_path:
                kwargs["out_path"] = out_path
            path = anatomy.build_model(**kwargs)
        else:
            from functools import partial

            from clgs.model_builder import build_model

            target = out_path or anatomy.model_path
            if not target:
                raise click.ClickException(f"the {name} plugin names no model_path: pass --out FILE")
            ids = _need(anatomy, "population", "list the population")()
            loader = _need(anatomy, "load_subject", "load subjects")
            template = _need(anatomy, "load_template", "load the template")()
            path = build_model(template, {sid: partial(loader, sid) for sid in ids}, target, force=force, **settings)
        click.echo(f"{name}: model {path} ready ({time.perf_counter() - t0:.1f} s)")

    @group.command()
    @click.argument("scan_dir", type=click.Path(exists=True, file_okay=False))
    @click.argument("volume", type=click.Path(exists=True))
    def evaluate(scan_dir, volume):
        """Compare a reconstructed VOLUME (.npy/.nii[.gz], or a folder with volume.npy) with the truth of SCAN_DIR."""
        from clgs.io.scan import Scan
        from clgs.io.volume import load_volume

        if os.path.isdir(volume):
            volume = os.path.join(volume, "volume.npy")
        scan = Scan.load(scan_dir)
        loaded = load_volume(volume)
        _echo_metrics(evaluate_volume(anatomy, scan, loaded[0]))

    @group.command()
    @click.option("--subject", "subject_id", default=None, help="held-out subject (default: the first)")
    @click.option("--views", default=5, show_default=True)
    @click.option("--method", default=None, help="default: shape when the anatomy has a model, else r2gs")
    @click.option("--out", default=None, type=click.Path(file_okay=False), help="keep outputs here")
    @click.option("--iterations", default=1000, show_default=True,
                  help="optimisation steps for iterative methods (the papers use 30000: hours on a CPU)")
    @click.option("--seed", default=0, show_default=True)
    @click.option("--set", "settings", multiple=True, metavar="KEY=VALUE", help="method option (repeatable)")
    def demo(subject_id, views, method, out, iterations, seed, settings):
        """Simulate a held-out subject, reconstruct it from few views, print error vs time."""
        import math
        import tempfile

        held = _need(anatomy, "test_subjects", "pick a held-out subject")()
        subject_id = subject_id or (held[0] if held else None)
        if subject_id is None:
            raise click.UsageError("the plugin has no held-out subjects: give --subject")
        method = method or default_method(anatomy)
        t0 = time.perf_counter()
        subject = _need(anatomy, "load_subject", "load a subject")(subject_id)
        scan = simulate_subject(anatomy, subject, views, math.radians(float(scene.get("arc_deg", 180.0))), True, seed)
        click.echo(f"{name} demo: subject {subject_id}, {views} views, method {method} "
                   f"(simulated in {time.perf_counter() - t0:.1f} s)")
        work = out or tempfile.mkdtemp(prefix=f"clgs-{name}-demo-")
        scan.save(os.path.join(work, "scan"), overwrite=True)
        t1 = time.perf_counter()
        opts = _parse_options(settings)
        if method_accepts(method, "iterations"):
            opts.setdefault("iterations", iterations)
        result = run_reconstruct(scan, anatomy, method, out=os.path.join(work, "recon"), **opts)
        elapsed = time.perf_counter() - t1
        history = result.get("history") or (result.get("info") or {}).get("history")
        if history:
            click.echo("  iteration   time (s)   metrics")
            for row in history:
                row = dict(row)
                it, tt = row.pop("iteration", ""), row.pop("time", row.pop("seconds", float("nan")))
                click.echo(f"  {it!s:>9} {tt:10.1f}   " + "  ".join(
                    f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
        click.echo(f"reconstructed in {elapsed:.1f} s; final error:")
        _echo_metrics(evaluate_volume(anatomy, scan, result["volume"]))
        click.echo(f"outputs in {work}")

    @group.command()
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
        if not path or not os.path.exists(path):
            click.echo(f"  model     not built ({path or 'no path'}): run `clgs {name} build-model`")
            return
        from clgs.shape_model import read_metadata

        meta = read_metadata(path)
        click.echo(f"  model     {path}")
        click.echo(f"            {meta.get('n_modes')} modes on grid {tuple(meta.get('grid_shape', ()))}, "
                   f"variance kept {100 * meta.get('variance_kept', float('nan')):.1f} %, "
                   f"{len(meta.get('population', []))} subjects")
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

    for cmd in anatomy.commands or []:
        if not isinstance(cmd, click.Command):
            raise click.ClickException(f"{name} plugin ({anatomy.package}): extra commands must be click commands, "
                                       f"got {type(cmd).__name__}")
        if cmd.name in group.commands:
            raise click.ClickException(f"{name} plugin ({anatomy.package}): command {cmd.name!r} clashes with a "
                                       "generic anatomy command")
        group.add_command(cmd)
    return group
