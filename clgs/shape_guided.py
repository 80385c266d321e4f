"""Shape-guided Gaussian splatting (Poudel et al.): Gaussians bound to an anatomy's shape model.

Two sets of Gaussians are optimised together against the projections:

* ``shape`` (Gs): laid out on the template (:mod:`clgs.shape_init`); their centres follow the
  shape model, ``p_j = p_ref_j + u(alpha)(p_ref_j)`` with ``u = exp(v(alpha)) - id``, so one
  vector ``alpha`` of mode coefficients moves all of them at once and keeps the bone a plausible
  bone. Their scale, rotation and density are free. They are never densified.
* ``free`` (Gz): R2-Gaussian's Gaussians (FDK initialisation, densification) for everything the
  anatomy does not explain, initialised only outside the template's bone.

Loss: ``L1 + 0.25 D-SSIM + 0.05 TV + lambda_shape |alpha|^2 + lambda_density L_density`` with
``L_density = mean_x m(x) w(x) (V_s(x) - atlas_mean(x'))^2``, ``w = exp(-atlas_var(x') / s^2)``,
over a random strided sub-grid covering the volume (a fresh offset every iteration), ``V_s`` the
field of the shape set alone, ``x'`` the point carried back into the template by the current
deformation (two fixed-point steps of ``x' = x - u(x')``), and ``m`` the template's bone mask at
``x'``: the atlas describes bone, and soft tissue is the free set's job.

The scan's world frame is taken to be the template's frame (the anatomy's own simulator scans in
it; a user's mesh is aligned to the template first). The ablation switches: ``shape_prior=False``
turns the shape set into ordinary free-moving Gaussians (positions learnt directly, "density init
only"); ``density_prior=False`` drops ``L_density``.

Units are those of :mod:`clgs.r2gs` (training units: scene lengths, values x ``value_scale``);
the atlas is converted the same way.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from clgs.evaluation import bone_surface  # the outer bone surface written with the outputs
from clgs.gaussians import GaussianSet, Schedule, init_from_volume, r2gs_schedules
from clgs.r2gs import (JsonConfig, fdk_volume, gaussians_in_scan_units, make_trainer, r2gs_losses, restore,
                       run_config, value_scale_from, volume_box, voxelize_volume)
from clgs.trainer import LossTerm, Trainer

CHECKPOINT = "checkpoint.pt"


@dataclass
class ShapeGuidedConfig(JsonConfig):
    """The paper's defaults (35k shape-guided + 15k free Gaussians, 30k iterations)."""

    iterations: int = 30_000
    n_shape: int = 35_000
    n_free: int = 15_000
    tau: float = 0.5
    boundary_weight: float = 4.0
    shape_prior: bool = True  # bind the shape set to the shape model (False: "density init only")
    density_prior: bool = True
    lambda_shape: float = 1e-4
    lambda_density: float = 0.5
    density_s: float = 0.05
    density_points: int = 32  # sub-grid points per axis for L_density
    lambda_dssim: float = 0.25
    lambda_tv: float = 0.05
    tv_size: int = 32
    lr_alpha: float = 0.1
    alpha_freeze: int = 50
    lr_density: float = 0.01
    lr_scale: float = 0.005
    lr_rotation: float = 0.01
    init_threshold: float = 0.05
    density_factor: float = 0.15
    densify_start: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    grad_threshold: float = 5e-5
    densify_scale_threshold: float = 0.1
    min_density: float = 1e-5
    max_gaussians: int = 500_000
    scale_bounds: tuple | None = (0.0005, 0.5)
    projector_mode: str = "affine"
    backend: str = "cl"
    seed: int = 0
    value_scale: float | None = None
    log_every: int = 500
    checkpoint_every: int = 1000
    schedule_iterations: int | None = None

    KIND = "shape-guided"


# ---------------------------------------------------------------------- the shape-guided set
class ShapeGuidedSet(GaussianSet):
    """Gaussians whose centres are ``p_ref + u(alpha)(p_ref)`` (mm), mapped to the scene.

    Leaves: ``alpha`` (M,), raw scales, quaternions, raw densities. ``p_ref`` is fixed."""

    MIN_SQUARINGS = 2

    def __init__(self, p_ref_mm, scales, quats, densities, *, shape_model, geometry, box, scale_bounds,
                 schedules, alpha=None, name: str = "shape", raw: bool = False):
        dt = torch.float32
        self.shape_model = shape_model.to(dt) if shape_model.dtype != dt else shape_model
        self.p_ref = torch.as_tensor(np.asarray(p_ref_mm, np.float64), dtype=dt)
        self._origin = torch.as_tensor(np.asarray(geometry.offOrigin[::-1], np.float64), dtype=dt)
        self._scale = float(geometry.scale)
        placeholder = torch.zeros((len(self.p_ref), 3), dtype=dt)
        super().__init__(placeholder, scales, quats, densities, box=box, scale_bounds=scale_bounds,
                         schedules=schedules, densify=False, name=name, raw=raw)
        del self.params["means"]
        a = torch.zeros(self.shape_model.n_modes, dtype=dt) if alpha is None else torch.as_tensor(alpha, dtype=dt)
        self.params = {"alpha": a.detach().clone().requires_grad_(True), **self.params}
        self.last_u = None  # the latest displacement field (detached), for the density prior

    def __len__(self):
        return int(self.p_ref.shape[0])

    @property
    def alpha(self) -> torch.Tensor:
        return self.params["alpha"]

    def displacement(self) -> torch.Tensor:
        """u(alpha) on the model grid. Squarings follow the half-cell rule with a floor of
        ``MIN_SQUARINGS`` (2, not the model's default 4): on the femur model at alpha = 3 sigma
        the map then differs from a 12-squaring one by 0.64 mm (0.2 voxel) and costs half as much,
        which matters since this runs, forward and backward, every iteration."""
        from clgs.shape_model import exp_velocity

        u = exp_velocity(self.shape_model.velocity(self.alpha), self.shape_model.spacing,
                         min_squarings=self.MIN_SQUARINGS)
        self.last_u = u.detach()
        return u

    def centres_mm(self, u=None) -> torch.Tensor:
        u = self.displacement() if u is None else u
        return self.p_ref + self.shape_model.sample(u, self.p_ref)

    def tensors(self):
        p = self.params
        means = (self.centres_mm() - self._origin) * self._scale
        return means, self.scale_activation(p["scales"]), p["quats"], F.softplus(p["densities"])

    def to_template(self, points_mm: torch.Tensor) -> torch.Tensor:
        """Points of the subject carried back to the template: x' = x - u(x'), two fixed-point steps."""
        if self.last_u is None:
            with torch.no_grad():
                self.displacement()
        x = points_mm
        for _ in range(2):
            x = points_mm - self.shape_model.sample(self.last_u, x)
        return x

    def to_numpy(self) -> dict:
        out = super().to_numpy()
        out["alpha"] = self.alpha.detach().numpy().astype(np.float32)
        out["p_ref_mm"] = self.p_ref.numpy().astype(np.float32)
        return out

    def state_dict(self) -> dict:
        return {**super().state_dict(), "p_ref": self.p_ref.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.p_ref = state["p_ref"].clone()
        for k in self.params:
            self.params[k] = state[k].detach().clone().requires_grad_(True)
        self.last_u = None


def shape_schedules(cfg: ShapeGuidedConfig, iterations: int, *, free_means: bool) -> dict:
    """The paper's learning rates for the shape set: alpha 0.1 decaying to 1% by the midpoint and
    frozen for the first ``alpha_freeze`` iterations; density and scale constant; rotation to 10%."""
    half = max(iterations // 2 - cfg.alpha_freeze, 1)
    sched = {
        "alpha": Schedule(cfg.lr_alpha, cfg.lr_alpha * 0.01, half, start=cfg.alpha_freeze, frozen_before_start=True),
        "densities": Schedule(cfg.lr_density),
        "scales": Schedule(cfg.lr_scale),
        "quats": Schedule(cfg.lr_rotation, cfg.lr_rotation * 0.1, iterations),
    }
    if free_means:
        sched["means"] = r2gs_schedules(iterations)["means"]
    return sched


# ---------------------------------------------------------------------- priors
def shape_prior_term(set_name: str = "shape"):
    """|alpha|^2 of the shape set."""

    def fn(ctx):
        s = _set(ctx.trainer, set_name)
        return (s.alpha * s.alpha).sum()

    return fn


def _set(trainer, name):
    for s in trainer.sets:
        if s.name == name:
            return s
    raise KeyError(name)


def random_subgrid(grid, n: int, generator: torch.Generator):
    """An ``n^3`` strided grid spanning ``grid``'s box with a random sub-stride offset."""
    from clgs.geometry import Grid

    shape = np.asarray(grid.shape)  # (Z, Y, X)
    sp = np.asarray(grid.spacing, float)  # (x, y, z)
    counts = np.minimum(shape, n)
    extent = (shape[::-1] - 1) * sp  # (x, y, z)
    step = np.where(counts[::-1] > 1, extent / np.maximum(counts[::-1], 1), 0.0)
    offset = torch.rand(3, generator=generator, dtype=torch.float64).numpy() * step
    origin = np.asarray(grid.origin, float) + offset
    return Grid(tuple(int(c) for c in counts), tuple(origin), tuple(np.where(step > 0, step, sp)))


class DensityPrior:
    """``L_density`` of the module doc, evaluated lazily per iteration."""

    def __init__(self, atlas, template, geometry, value_scale: float, s: float, n_points: int,
                 set_name: str = "shape"):
        self.atlas, self.template, self.geometry = atlas, template, geometry
        self.value_scale = float(value_scale)
        self.s2 = float(s) ** 2
        self.n_points = int(n_points)
        self.set_name = set_name
        lo, hi = template.bounds()
        self._lo, self._hi = torch.as_tensor(lo, dtype=torch.float32), torch.as_tensor(hi, dtype=torch.float32)
        self._label = torch.as_tensor(template.label.astype(np.float32))[None, None]

    def _inside_template(self, pts_mm: torch.Tensor) -> torch.Tensor:
        g = ((pts_mm - self._lo) / (self._hi - self._lo) * 2 - 1).reshape(1, 1, 1, -1, 3)
        m = F.grid_sample(self._label, g, mode="bilinear", padding_mode="zeros", align_corners=True)
        return m.reshape(-1)

    def __call__(self, ctx):
        trainer = ctx.trainer
        s = _set(trainer, self.set_name)
        grid = random_subgrid(self.geometry.volume_grid(scene=True), self.n_points, ctx.generator)
        n = len(s)
        offset = 0
        for other in trainer.sets:  # the shape set's rows within the concatenated scene tensors
            if other is s:
                break
            offset += len(other)
        tensors = tuple(t[offset:offset + n] for t in ctx.tensors)
        v_s = ctx.voxelize(grid, tensors).reshape(-1)
        with torch.no_grad():
            pts = torch.as_tensor(grid.points().reshape(-1, 3), dtype=torch.float32)
            pts_mm = pts / self.geometry.scale + torch.as_tensor(np.asarray(self.geometry.offOrigin[::-1]),
                                                                 dtype=torch.float32)
            x_t = s.to_template(pts_mm) if isinstance(s, ShapeGuidedSet) else pts_mm
            mean = self.atlas.mean_at(x_t.double()).float() * self.value_scale
            var = self.atlas.var_at(x_t.double()).float() * self.value_scale ** 2
            w = torch.exp(-var / self.s2) * self._inside_template(x_t)
        return (w * (v_s - mean) ** 2).mean()


# ---------------------------------------------------------------------- building a run
@dataclass
class ShapeGuidedResult:
    volume: np.ndarray
    gaussians: dict
    alpha: np.ndarray
    log: object
    trainer: Trainer = field(repr=False)
    value_scale: float
    interrupted: bool
    out_dir: Path | None
    summary: str
    seconds: float


def _free_init_volume(fdk, geometry, template) -> np.ndarray:
    """The FDK volume with the template's bone blanked out (free Gaussians start outside it)."""
    pts = geometry.volume_grid(scene=False).points().reshape(-1, 3)
    inside = template.sdf_at(pts).reshape(fdk.shape) < 0
    vol = np.array(fdk, np.float32, copy=True)
    vol[inside] = float(vol.min())
    return vol


def build_trainer(scan, anatomy_parts, cfg: ShapeGuidedConfig, out_dir=None, *, progress=False, fdk=None,
                  state=None) -> Trainer:
    """Initial sets, losses and trainer for one scan. ``anatomy_parts`` = (template, shape_model, atlas);
    the shape model or atlas may be None, and their terms are then left out."""
    from clgs.shape_init import initialise

    template, shape_model, atlas = anatomy_parts
    geo = scan.geometry
    box = volume_box(geo)
    iters = cfg.schedule_iterations or cfg.iterations
    if cfg.value_scale is None or (state is None and cfg.n_free > 0):
        fdk = fdk_volume(scan) if fdk is None else fdk
        if cfg.value_scale is None:
            cfg.value_scale = value_scale_from(fdk)
    bound = cfg.shape_prior and shape_model is not None
    sched = shape_schedules(cfg, iters, free_means=not bound)
    if state is None:
        init = initialise(template, atlas, geo, cfg.n_shape, tau=cfg.tau, boundary_weight=cfg.boundary_weight,
                          seed=cfg.seed, backend=cfg.backend)
        scales = init.scales * geo.scale
        dens = init.densities * cfg.value_scale
    else:
        n = state["sets"]["shape"]["scales"].shape[0]
        init = None
        scales, dens = np.full((n, 3), 0.01), np.full(n, 0.01)
    quats = init.quats if init is not None else np.tile([1.0, 0, 0, 0], (len(scales), 1))
    centres = init.centres if init is not None else np.zeros((len(scales), 3))
    common = dict(box=box, scale_bounds=cfg.scale_bounds, name="shape")
    if bound:
        shape_set = ShapeGuidedSet(centres, scales.astype(np.float32), quats.astype(np.float32),
                                   dens.astype(np.float32), shape_model=shape_model, geometry=geo,
                                   schedules=sched, **common)
    else:
        shape_set = GaussianSet(geo.world_to_scene(centres).astype(np.float32), scales.astype(np.float32),
                                quats.astype(np.float32), dens.astype(np.float32), schedules=sched,
                                densify=False, **common)
    sets = [shape_set]
    if cfg.n_free > 0:
        fsched = r2gs_schedules(iters)
        kw = dict(box=box, scale_bounds=cfg.scale_bounds, schedules=fsched, name="free", densify=True)
        if state is None:
            vol = _free_init_volume(fdk, geo, template) * cfg.value_scale
            free = init_from_volume(vol, geo.volume_grid(scene=True), n_gaussians=cfg.n_free,
                                    threshold=cfg.init_threshold, density_factor=cfg.density_factor,
                                    seed=cfg.seed + 1, **kw)
        else:
            e = np.zeros((0, 3), np.float32)
            free = GaussianSet(e, e, np.zeros((0, 4), np.float32), np.zeros(0, np.float32), raw=True, **kw)
        sets.append(free)
    losses = r2gs_losses(cfg)
    if bound:
        losses.append(LossTerm("shape", cfg.lambda_shape, shape_prior_term()))
    if cfg.density_prior and atlas is not None:
        losses.append(LossTerm("density", cfg.lambda_density,
                               DensityPrior(atlas, template, geo, cfg.value_scale, cfg.density_s, cfg.density_points)))
    return make_trainer(scan, cfg, sets, losses, out_dir, progress)


def deformed_template_surface(template, shape_set) -> tuple:
    """The template surface carried onto the subject by the fitted alpha: (vertices mm, faces)."""
    if not isinstance(shape_set, ShapeGuidedSet):
        return None
    with torch.no_grad():
        u = shape_set.shape_model.displacement(shape_set.alpha.detach())
        v = torch.as_tensor(template.vertices, dtype=torch.float32)
        moved = v + shape_set.shape_model.sample(u, v)
    return moved.numpy().astype(np.float64), np.asarray(template.faces)


def reconstruct_shape_guided(scan, anatomy, out_dir=None, iterations: int = 30_000, *, resume: bool = False,
                             progress: bool = True, fdk=None, level: float | None = None,
                             **settings) -> ShapeGuidedResult:
    """Reconstruct ``scan`` with the shape-guided method and the parts of ``anatomy``.

    ``anatomy``: a :class:`clgs.anatomy.Anatomy` (its template, shape model and atlas are loaded)
    or a tuple (template, shape_model, atlas). ``settings``: :class:`ShapeGuidedConfig` fields.
    ``out_dir`` receives volume.nii.gz, gaussians.npz, alpha.json, log.csv/png, summary.txt,
    surface.stl (the reconstruction's bone surface at ``level``, 1/mm) and shape_surface.stl (the
    template deformed by the fitted alpha); checkpoints allow ``resume``.
    """
    from clgs.io.scan import Scan

    if not isinstance(scan, Scan):
        scan = Scan.load(scan)
    parts = anatomy if isinstance(anatomy, tuple) else load_anatomy_parts(anatomy)
    cfg, state = run_config(ShapeGuidedConfig, iterations, settings, resume, out_dir)
    t0 = time.perf_counter()
    trainer = build_trainer(scan, parts, cfg, out_dir, progress=progress, fdk=fdk, state=state)
    restore(trainer, state, cfg)
    trainer.fit()
    volume = voxelize_volume(trainer) / np.float32(cfg.value_scale)
    shape_set = trainer.sets[0]
    alpha = shape_set.alpha.detach().numpy().copy() if isinstance(shape_set, ShapeGuidedSet) else np.zeros(0)
    seconds = time.perf_counter() - t0
    if out_dir is not None:
        write_outputs(trainer, out_dir, cfg.value_scale, volume, parts[0], alpha, level)
    return ShapeGuidedResult(volume=volume, gaussians=gaussians_in_scan_units(trainer, cfg.value_scale),
                             alpha=alpha, log=trainer.log, trainer=trainer, value_scale=cfg.value_scale,
                             interrupted=trainer.interrupted, out_dir=None if out_dir is None else Path(out_dir),
                             summary=trainer.log.summary(), seconds=seconds)


def load_anatomy_parts(anatomy) -> tuple:
    """(template, shape model or None, atlas or None) from an Anatomy's lazy loaders."""
    if anatomy.load_template is None:
        raise ValueError(f"anatomy {anatomy.name!r} provides no template; the shape-guided method needs one")
    template = anatomy.load_template()
    model = anatomy.load_shape_model() if anatomy.load_shape_model else None
    atlas = anatomy.load_atlas() if anatomy.load_atlas else None
    return template, model, atlas


def write_outputs(trainer, out_dir, value_scale, volume, template, alpha, level=None) -> dict:
    """The r2gs outputs plus alpha and the two surfaces; each file atomically."""
    from clgs.io import atomic
    from clgs.io.mesh import save_mesh
    from clgs.r2gs import write_outputs as write_common

    out_dir = Path(out_dir)
    paths = write_common(trainer, out_dir, value_scale, volume)
    paths["alpha"] = atomic.write_json(out_dir / "alpha.json", {"alpha": [float(a) for a in alpha]})
    moved = deformed_template_surface(template, trainer.sets[0])
    if moved is not None:
        paths["shape_surface"] = save_mesh(out_dir / "shape_surface.stl", *moved)
    surf = bone_surface(volume, trainer.geometry, level)
    if surf is not None:
        paths["surface"] = save_mesh(out_dir / "surface.stl", *surf)
    return paths


# ---------------------------------------------------------------------- `--method shape`
def _anatomy_for(scan, anatomy):
    if anatomy is not None and not isinstance(anatomy, str):
        return anatomy
    from clgs import plugins

    name = anatomy or (scan.meta or {}).get("anatomy")
    if not name:
        raise ValueError("the shape-guided method needs an anatomy: pass --anatomy NAME (see `clgs anatomies`) "
                         "or reconstruct with `clgs <anatomy> reconstruct`")
    return plugins.get_anatomy(name)


def run_method(scan, out_dir=None, iterations: int = 30_000, anatomy=None, resume: bool = False,
               progress: bool = True, **settings) -> dict:
    """The ``shape`` entry of :mod:`clgs.methods`."""
    import click

    anatomy = _anatomy_for(scan, anatomy)
    result = reconstruct_shape_guided(scan, anatomy, out_dir, iterations, resume=resume, progress=progress,
                                      **settings)
    click.echo(result.summary, err=True)
    if result.interrupted:
        where = f"; continue with --resume --out {out_dir}" if out_dir is not None else ""
        click.echo(f"interrupted at iteration {result.trainer.iteration}: outputs so far written{where}", err=True)
    info = {"iterations": result.trainer.iteration, "n_gaussians": result.trainer.n_gaussians,
            "training_seconds": result.trainer.seconds, "seconds": result.seconds,
            "value_scale": result.value_scale, "interrupted": result.interrupted,
            "alpha": [float(a) for a in result.alpha], "history": result.log.rows}
    files = sorted(str(p) for p in Path(out_dir).iterdir()) if out_dir is not None else []
    return {"volume": result.volume, "files": files, "info": info}


def click_options() -> list:
    import click

    from clgs.r2gs import click_options as r2gs_options

    keep = {"iterations", "resume", "seed", "backend", "projector_mode", "lambda_tv", "lambda_dssim", "log_every",
            "checkpoint_every", "progress", "max_gaussians"}
    opts = [o for o in r2gs_options() if o.name in keep]
    return opts + [
        click.Option(["--anatomy", "anatomy"], default=None,
                     help="anatomy plugin giving template, shape model and atlas [default: the scan's]"),
        click.Option(["--shape-gaussians", "n_shape"], type=click.IntRange(min=1), default=None,
                     help="shape-guided Gaussians [default: 35000]"),
        click.Option(["--free-gaussians", "n_free"], type=click.IntRange(min=0), default=None,
                     help="free (R2-Gaussian) Gaussians at the start [default: 15000]"),
        click.Option(["--tau", "tau"], type=click.FloatRange(0, 1, min_open=True), default=None,
                     help="thinning along the surface normal [default: 0.5]"),
        click.Option(["--shape-prior/--no-shape-prior", "shape_prior"], default=None,
                     help="bind the shape-guided Gaussians to the shape model [default: on]"),
        click.Option(["--density-prior/--no-density-prior", "density_prior"], default=None,
                     help="atlas density prior on the shape-guided Gaussians [default: on]"),
    ]


def _method():
    from clgs.methods import Method

    return Method("shape", run_method, options=click_options, atomic_dir=False,
                  help="shape-guided Gaussian splatting with an anatomy's shape model and density atlas")


METHOD = _method()

__all__ = ["ShapeGuidedConfig", "ShapeGuidedSet", "ShapeGuidedResult", "reconstruct_shape_guided",
           "build_trainer", "bone_surface", "DensityPrior", "random_subgrid"]
