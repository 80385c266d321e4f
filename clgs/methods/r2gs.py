"""R2-Gaussian reconstruction (Zha et al., NeurIPS 2024) on clgs's kernels: the ``r2gs`` method.

From Python::

    from clgs.io.scan import Scan
    from clgs.methods.r2gs import reconstruct_r2gs
    result = reconstruct_r2gs(Scan.load("scan_dir"), out_dir="run", iterations=10_000)
    result.volume          # (Z, Y, X) float32, the scan's units (1/mm)
    print(result.summary)

From the shell: ``clgs reconstruct scan_dir --method r2gs --iterations 10000 --out run``.

The run folder holds ``volume.nii.gz``, ``gaussians.npz``, ``log.csv``, ``log.png``,
``summary.txt``, ``config.json`` and ``checkpoint.pt`` (``resume=True`` / ``--resume`` continues
from it bit for bit).

Units (normalisation). The papers' learning rates assume volumes of order 1 in a scene scaled
to [-1, 1]^3 (R2-Gaussian's volumes are in [0, 1]). A scan holds line integrals in mm of an
attenuation in 1/mm, so training works in *training units*:

* lengths in scene units: the projections are multiplied by ``geometry.scale`` (mm -> scene), and
  the projector's output (mm) by the same factor;
* values scaled by ``value_scale = 1 / p99.9(FDK volume)``, so the FDK's 99.9th percentile
  (robust to streaks and hot voxels) is 1 and the Gaussians' densities are of order 1.

So the training target is ``projections x geometry.scale x value_scale``; every output (volume,
Gaussian densities) is divided by ``value_scale`` and is back in 1/mm. ``value_scale`` can be
given explicitly (e.g. to compare runs on the same footing).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from clgs.fit import losses as L
from clgs.fit.gaussians import Densifier, GaussianSet, init_from_volume, init_random, r2gs_schedules
from clgs.fit.trainer import Backend, LossTerm, Trainer
from clgs.fit.training_log import TrainingLog

CHECKPOINT = "checkpoint.pt"


class JsonConfig:
    """JSON round trip of a method's settings (a dataclass); unknown keys and values of the wrong
    kind or out of range are a clear error (checked when the settings are made)."""

    KIND = "method"
    CHOICES: dict = {}  # setting -> allowed strings
    POSITIVE: frozenset = frozenset()  # numbers that must be > 0 (every number must be >= 0)
    AT_LEAST: dict = {}  # setting -> smallest allowed value

    def __post_init__(self):
        for f in fields(self):
            setattr(self, f.name, self._checked(f.name, str(f.type), getattr(self, f.name)))

    def _checked(self, name: str, kind: str, value):
        where = f"{self.KIND} setting {name}"
        if value is None:
            if "None" in kind:
                return None
            raise ValueError(f"{where} must be given (got null)")
        base = kind.split("|")[0].strip()
        if base == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise ValueError(f"{where} must be true or false, got {value!r}")
            return bool(value)
        if base == "str":
            if not isinstance(value, str):
                raise ValueError(f"{where} must be a string, got {value!r}")
            allowed = self.CHOICES.get(name)
            if allowed and value not in allowed:
                raise ValueError(f"{where} must be one of {', '.join(allowed)}, got {value!r}")
            return value
        if base == "tuple":
            return value
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"{where} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ValueError(f"{where} must be finite, got {value!r}")
        if base == "int":
            if value != int(value):
                raise ValueError(f"{where} must be a whole number, got {value!r}")
            value = int(value)
        else:
            value = float(value)
        low = self.AT_LEAST.get(name, 0)
        if value < low or (name in self.POSITIVE and value <= 0):
            need = f"> 0" if name in self.POSITIVE else f">= {low:g}"
            raise ValueError(f"{where} must be {need}, got {value!r}")
        return value

    def to_json(self) -> dict:
        d = asdict(self)
        if d.get("scale_bounds") is not None:
            d["scale_bounds"] = list(d["scale_bounds"])
        return d

    @classmethod
    def from_json(cls, d: dict):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown {cls.KIND} settings: {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        d = dict(d)
        if d.get("scale_bounds") is not None:
            d["scale_bounds"] = tuple(d["scale_bounds"])
        return cls(**d)


@dataclass
class GaussianFitConfig(JsonConfig):
    """Settings every Gaussian reconstruction shares (R2-Gaussian's defaults): loss weights,
    FDK-based initialisation, densification, scale bounds, the projector and the run's logging."""

    iterations: int = 30_000
    init_threshold: float = 0.05  # of the FDK range
    density_factor: float = 0.15
    lambda_dssim: float = 0.25
    lambda_tv: float = 0.05
    tv_size: int = 32
    densify_start: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    grad_threshold: float = 5e-5
    densify_scale_threshold: float = 0.1  # of the volume extent: at most this -> clone, else split
    min_density: float = 1e-5
    max_gaussians: int = 500_000
    scale_bounds: tuple | None = (0.0005, 0.5)  # of the volume extent; None -> exp scales
    scale_floor: float | None = 0.4  # smallest scale >= this x the scan's resolution (None: off)
    projector_mode: str = "affine"  # "affine" (R2-Gaussian) | "exact"
    backend: str = "cl"
    seed: int = 0
    value_scale: float | None = None  # None -> 1 / p99.9 of the FDK volume
    log_every: int = 500
    checkpoint_every: int = 1000
    schedule_iterations: int | None = None  # length of the lr decays (default: iterations)

    CHOICES = {"projector_mode": ("affine", "exact"), "backend": ("cl", "torch")}
    POSITIVE = frozenset({"value_scale"})
    AT_LEAST = {"iterations": 1, "densify_interval": 1, "max_gaussians": 1, "tv_size": 2, "schedule_iterations": 1}

    def __post_init__(self):
        super().__post_init__()
        b = self.scale_bounds
        if b is not None:
            try:
                lo, hi = (float(x) for x in b)
            except (TypeError, ValueError):
                raise ValueError(f"{self.KIND} setting scale_bounds must be two numbers (or null), got {b!r}") from None
            if not (0 < lo < hi and math.isfinite(hi)):
                raise ValueError(f"{self.KIND} setting scale_bounds must satisfy 0 < low < high, got {b!r}")
            self.scale_bounds = (lo, hi)


@dataclass
class R2GSConfig(GaussianFitConfig):
    """R2-Gaussian's defaults (iterations, initialisation, loss weights, densification)."""

    n_gaussians: int = 50_000  # initial count (fewer when fewer voxels pass the threshold)
    init: str = "fdk"  # "fdk" | "random"

    KIND = "r2gs"
    CHOICES = {**GaussianFitConfig.CHOICES, "init": ("fdk", "random")}
    AT_LEAST = {**GaussianFitConfig.AT_LEAST, "n_gaussians": 1}


@dataclass
class R2GSResult:
    """What a run returns: the volume and Gaussians in the scan's units, the log, the trainer."""

    volume: np.ndarray
    gaussians: dict
    log: TrainingLog
    trainer: Trainer = field(repr=False)
    value_scale: float
    interrupted: bool
    out_dir: Path | None
    summary: str
    files: dict = field(default_factory=dict)  # output name -> path


# ---------------------------------------------------------------------- pieces
def volume_box(geometry) -> tuple:
    """Half-extents (x, y, z) of the reconstruction volume in scene units."""
    return tuple(0.5 * geometry.sVoxel[::-1] * geometry.scale)


def scale_bounds_for(geometry, scale_bounds, scale_floor):
    """The scale bounds (fractions of the volume extent) a scan allows: ``scale_bounds`` with its
    lower end raised to ``scale_floor`` x :attr:`Geometry.resolution_mm` when that is larger.

    Why: with only the extent's 0.05 % as the floor (R2-Gaussian's, one eighth of a voxel on its
    256^3 scans), a 64^3 scan lets Gaussians shrink to 1/30 of a voxel; long runs then fit the
    views' noise with sub-voxel needles that voxel-centre sampling misses, and 3D PSNR falls while
    the projection PSNR still rises (measured: 30.1 dB at 2000 iterations, 23.7 at 5000)."""
    if scale_bounds is None:
        return None
    lo, hi = (float(b) for b in scale_bounds)
    if scale_floor:
        lo = max(lo, float(scale_floor) * geometry.resolution_mm / float(np.max(geometry.sVoxel)))
    if not lo < hi:
        raise ValueError(f"the smallest Gaussian scale ({lo:.4g} of the volume, from scale_bounds and scale_floor "
                         f"{scale_floor} x the scan's {geometry.resolution_mm:.3g} mm resolution) is not below the "
                         f"largest ({hi:.4g}); lower scale_floor or raise scale_bounds[1]")
    return lo, hi


def fdk_volume(scan) -> np.ndarray:
    from clgs.ct.fdk import fdk

    return np.asarray(fdk(scan.projections, scan.geometry), dtype=np.float32)


def value_scale_from(volume: np.ndarray) -> float:
    """``1 / p99.9`` of a volume (its robust maximum); see the module doc."""
    p = float(np.percentile(np.asarray(volume, np.float32), 99.9))
    if not (math.isfinite(p) and p > 0):
        raise ValueError(f"the FDK volume's 99.9th percentile is {p}: the projections look empty or "
                         "negative; give value_scale explicitly")
    return 1.0 / p


def tv_term(size: int):
    """TV of the model voxelised on a random ``size^3`` block of the volume grid, shifted by a random
    fraction of a voxel as R2-Gaussian places its patch anywhere (on the OpenCL
    backend one fused device pass: cull, field, TV and its gradient, see :mod:`clgs.fit.tv_patch`)."""

    def fn(ctx):
        from clgs.fit.tv_patch import patch_tv

        grid = ctx.geometry.volume_grid(scene=True)
        block = L.random_block(grid, size, ctx.generator, subvoxel=True)  # off the evaluation lattice
        return patch_tv(ctx.trainer.backend, ctx.tensors, block)

    return fn


def r2gs_losses(cfg: R2GSConfig) -> list:
    image = L.ImageTerms(dssim=cfg.lambda_dssim > 0)  # L1 and D-SSIM from one pass on the OpenCL backend
    return [
        LossTerm("l1", 1.0, image.l1),
        LossTerm("dssim", cfg.lambda_dssim, image.dssim),
        LossTerm("tv", cfg.lambda_tv, tv_term(cfg.tv_size)),
    ]


def make_evaluator(scan, value_scale: float):
    """Figures for the log: projection PSNR over the training views (peak = the largest measured
    value) and, with a ground truth, 3D PSNR / SSIM of the voxelised volume (clgs.metrics)."""
    truth = None if scan.truth is None else np.asarray(scan.truth, np.float32)

    def evaluate(trainer: Trainer) -> dict:
        tensors = tuple(t.detach() for t in trainer.scene_tensors())
        out = {}
        views = trainer.views
        mse, peak = 0.0, 0.0
        for i in range(0, len(views), 8):
            chunk = views[i:i + 8]
            pred = trainer.backend.project(*tensors, trainer.geometry, chunk) * trainer.render_scale
            target = trainer.projections[chunk]
            mse += float(((pred - target) ** 2).sum())
            peak = max(peak, float(target.max()))
        mse /= len(views) * trainer.projections[0].numel()
        out["proj_psnr"] = 10 * math.log10(peak * peak / mse) if mse > 0 and peak > 0 else float("inf")
        if truth is not None:
            from clgs import metrics

            vol = voxelize_volume(trainer, tensors) / value_scale
            out["psnr3d"] = float(metrics.psnr3d(vol, truth))
            out["ssim3d"] = float(metrics.ssim3d(vol, truth))
        return out

    return evaluate


def voxelize_volume(trainer: Trainer, tensors=None) -> np.ndarray:
    """The whole model on the reconstruction grid, training units, (Z, Y, X) float32."""
    with torch.no_grad():
        tensors = tensors or tuple(t.detach() for t in trainer.scene_tensors())
        vol = trainer.backend.voxelize(*tensors, trainer.geometry.volume_grid(scene=True))
    return vol.numpy().astype(np.float32)


def build_trainer(scan, cfg: R2GSConfig, out_dir=None, *, progress=False, fdk=None, state=None,
                  gaussians=None) -> Trainer:
    """Everything but the loop: normalisation, initial Gaussians, losses, densifier, trainer.

    ``state`` (a loaded checkpoint) skips the initialisation; the checkpoint then overwrites it.
    ``gaussians``: initial (means, scales, quats, densities) in training units, instead of ``cfg.init``.
    """
    geo = scan.geometry
    box = volume_box(geo)
    sched = r2gs_schedules(cfg.schedule_iterations or cfg.iterations)
    kw = dict(box=box, scale_bounds=scale_bounds_for(geo, cfg.scale_bounds, cfg.scale_floor), schedules=sched,
              name="free", densify=True)
    if cfg.value_scale is None:
        fdk = fdk_volume(scan) if fdk is None else fdk
        cfg.value_scale = value_scale_from(fdk)
    if gaussians is not None:
        gset = GaussianSet(*(np.asarray(a, np.float32) for a in gaussians), **kw)
    elif state is not None:
        empty = np.zeros((0, 3), np.float32)
        gset = GaussianSet(empty, empty, np.zeros((0, 4), np.float32), np.zeros(0, np.float32), raw=True, **kw)
    elif cfg.init == "fdk":
        fdk = fdk_volume(scan) if fdk is None else fdk
        gset = init_from_volume(fdk * cfg.value_scale, geo.volume_grid(scene=True), n_gaussians=cfg.n_gaussians,
                                threshold=cfg.init_threshold, density_factor=cfg.density_factor, seed=cfg.seed, **kw)
    elif cfg.init == "random":
        gset = init_random(cfg.n_gaussians, seed=cfg.seed, **kw)
    else:
        raise ValueError(f"init must be 'fdk' or 'random', got {cfg.init!r}")
    return make_trainer(scan, cfg, [gset], r2gs_losses(cfg), out_dir, progress)


def make_trainer(scan, cfg, sets, losses, out_dir=None, progress=False) -> Trainer:
    """The trainer of a Gaussian method: training-unit projections, the densifier (it edits only
    sets marked ``densify``), the evaluator and checkpoints in ``out_dir``. ``cfg`` holds the
    shared settings (R2GSConfig's names); ``cfg.value_scale`` must be set."""
    geo = scan.geometry
    densifier = Densifier(geo, start=cfg.densify_start, until=cfg.densify_until, interval=cfg.densify_interval,
                          grad_threshold=cfg.grad_threshold, scale_threshold=cfg.densify_scale_threshold,
                          min_density=cfg.min_density, max_gaussians=cfg.max_gaussians)
    projections = np.asarray(scan.projections, np.float32) * np.float32(geo.scale * cfg.value_scale)
    out_dir = None if out_dir is None else Path(out_dir)
    return Trainer(
        sets, geo, projections, losses, iterations=cfg.iterations,
        backend=Backend(cfg.backend, cfg.projector_mode), render_scale=geo.scale, seed=cfg.seed,
        hooks=[densifier], evaluate=make_evaluator(scan, cfg.value_scale), log_every=cfg.log_every,
        checkpoint_every=cfg.checkpoint_every if out_dir is not None else 0,
        checkpoint_path=None if out_dir is None else out_dir / CHECKPOINT, progress=progress,
        config=cfg.to_json(),
    )


def run_config(config_cls, iterations: int | None, settings: dict, resume: bool, out_dir):
    """(settings, checkpoint or None) of a new run, or of a run resumed from ``out_dir``: a resumed
    run keeps its checkpoint's settings (only ``iterations`` may grow and ``backend`` change).

    ``iterations=None``: the default (30 000) for a new run; for a resumed one, the iterations it
    was started with (an interrupted run is finished, not extended)."""
    from clgs.fit import checkpoint as ckpt

    if iterations is not None and int(iterations) < 1:
        raise ValueError(f"iterations must be at least 1, got {iterations}")
    settings = dict(settings)
    if not resume:
        n = config_cls().iterations if iterations is None else int(iterations)
        return config_cls.from_json({**config_cls().to_json(), **settings, "iterations": n}), None
    if out_dir is None:
        raise ValueError("resume needs out_dir (the folder holding checkpoint.pt)")
    state = ckpt.load(Path(out_dir) / CHECKPOINT)
    try:
        saved = ckpt.loads(state["config"])
        if not isinstance(saved, dict):
            raise TypeError(type(saved).__name__)
    except (KeyError, TypeError, ValueError) as exc:
        raise ckpt.CheckpointError(f"{Path(out_dir) / CHECKPOINT} holds no readable run settings ({exc}): it "
                                   "cannot be resumed; start a new run") from None
    if "scale_floor" not in saved and any(f.name == "scale_floor" for f in fields(config_cls)):
        saved["scale_floor"] = None  # written before the floor existed: keep the bounds it trained with
    cfg = config_cls.from_json(saved)
    cfg.schedule_iterations = cfg.schedule_iterations or cfg.iterations
    planned = cfg.iterations if iterations is None else int(iterations)
    cfg.iterations = max(planned, int(state["iteration"]))
    if "backend" in settings:  # where to compute does not change the run's meaning
        cfg.backend = settings.pop("backend")
    if settings:
        raise ValueError(f"resume continues with the checkpoint's settings; drop {', '.join(sorted(settings))}")
    return cfg, state


def restore(trainer: Trainer, state, cfg) -> None:
    """Load a checkpoint into a freshly built trainer (no-op without one)."""
    if state is not None:
        trainer.load_state_dict(state)
        trainer.iterations = trainer.config["iterations"] = cfg.iterations


def gaussians_in_scan_units(trainer: Trainer, value_scale: float) -> dict:
    """Every set's Gaussians: scene units (means, scales) plus mm, densities in 1/mm."""
    geo = trainer.geometry
    out = {}
    for s in trainer.sets:
        g = s.to_numpy()
        prefix = "" if len(trainer.sets) == 1 else f"{s.name}_"
        out[prefix + "means"] = g["means"]
        out[prefix + "scales"] = g["scales"]
        out[prefix + "quats"] = g["quats"]
        out[prefix + "densities"] = (g["densities"] / value_scale).astype(np.float32)
        out[prefix + "means_mm"] = geo.scene_to_world(g["means"]).astype(np.float32)
        out[prefix + "scales_mm"] = (g["scales"] / geo.scale).astype(np.float32)
    out["value_scale"] = np.float64(value_scale)
    out["scene_scale"] = np.float64(geo.scale)
    return out


def write_outputs(trainer: Trainer, out_dir, value_scale: float, volume=None) -> dict:
    """Volume (NIfTI), Gaussians (npz), log (CSV + PNG), summary; each file atomically."""
    from clgs.io import atomic
    from clgs.io.volume import save_volume

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    volume = voxelize_volume(trainer) / np.float32(value_scale) if volume is None else volume
    paths = {
        "volume": save_volume(out_dir / "volume.nii.gz", volume, trainer.geometry),
        "gaussians": atomic.save_npz(out_dir / "gaussians.npz", **gaussians_in_scan_units(trainer, value_scale)),
        "log": trainer.log.write_csv(out_dir / "log.csv"),
        "config": atomic.write_json(out_dir / "config.json", trainer.config),
        "summary": atomic.write_text(out_dir / "summary.txt", trainer.log.summary() + "\n"),
    }
    if trainer.log.rows:
        paths["plot"] = trainer.log.plot(out_dir / "log.png", title=f"r2gs: {trainer.iteration} iterations")
    return paths


# ---------------------------------------------------------------------- the method
def reconstruct_r2gs(scan, out_dir=None, iterations: int | None = None, *, resume: bool = False,
                     progress: bool = True, fdk=None, **settings) -> R2GSResult:
    """Reconstruct ``scan`` (a :class:`clgs.io.scan.Scan` or a scan folder) with R2-Gaussian.

    ``settings`` are :class:`R2GSConfig` fields (``backend``, ``seed``, ``lambda_tv``, ...).
    ``out_dir`` gets the outputs and checkpoints (none without it). ``resume=True`` continues the
    run in ``out_dir`` from its checkpoint, with the checkpoint's settings, to the iterations it
    was started with, or to ``iterations`` when given (to train longer). ``iterations=None`` on a
    new run: 30 000, R2-Gaussian's. ``fdk``: a ready FDK volume (else computed). Ctrl-C stops cleanly:
    outputs so far are written and ``result.interrupted`` is True.
    """
    from clgs.io.scan import Scan

    if not isinstance(scan, Scan):
        scan = Scan.load(scan)
    cfg, state = run_config(R2GSConfig, iterations, settings, resume, out_dir)
    trainer = build_trainer(scan, cfg, out_dir, progress=progress, fdk=fdk, state=state)
    restore(trainer, state, cfg)
    trainer.fit()
    volume = voxelize_volume(trainer) / np.float32(cfg.value_scale)
    files = {}
    if out_dir is not None:
        files = {k: Path(v) for k, v in write_outputs(trainer, out_dir, cfg.value_scale, volume).items()}
        files["checkpoint"] = Path(out_dir) / CHECKPOINT
    return R2GSResult(volume=volume, gaussians=gaussians_in_scan_units(trainer, cfg.value_scale), log=trainer.log,
                      trainer=trainer, value_scale=cfg.value_scale, interrupted=trainer.interrupted,
                      out_dir=None if out_dir is None else Path(out_dir), summary=trainer.log.summary(),
                      files=files)


# ---------------------------------------------------------------------- `clgs reconstruct --method r2gs`
def run_method(scan, out_dir=None, iterations: int | None = None, resume: bool = False, progress: bool = True,
               **settings) -> dict:
    """The ``r2gs`` entry of :mod:`clgs.methods`: returns the volume, the files written and figures."""
    import click

    result = reconstruct_r2gs(scan, out_dir, iterations, resume=resume, progress=progress, **settings)
    click.echo(result.summary, err=True)
    if result.interrupted:
        where = f"; continue with --resume --out {out_dir}" if out_dir is not None else ""
        click.echo(f"interrupted at iteration {result.trainer.iteration}: outputs so far written{where}", err=True)
    info = {"iterations": result.trainer.iteration, "n_gaussians": result.trainer.n_gaussians,
            "training_seconds": result.trainer.seconds, "value_scale": result.value_scale,
            "interrupted": result.interrupted}
    return {"volume": result.volume, "files": {k: str(v) for k, v in result.files.items()}, "info": info}


def click_options() -> list:
    import click

    from clgs.methods import FiniteFloat, Seed

    return [
        click.Option(["--iterations", "iterations"], type=click.IntRange(min=1), default=None,
                     help="training iterations (one view each) [default: 30000]"),
        click.Option(["--resume", "resume"], is_flag=True, default=None,
                     help="continue the run in --out from its checkpoint (bit for bit)"),
        click.Option(["--gaussians", "n_gaussians"], type=click.IntRange(min=1), default=None,
                     help="initial number of Gaussians [default: 50000]"),
        click.Option(["--max-gaussians", "max_gaussians"], type=click.IntRange(min=1), default=None,
                     help="cap on the number of Gaussians while densifying [default: 500000]"),
        click.Option(["--init", "init"], type=click.Choice(["fdk", "random"]), default=None,
                     help="initialise from an FDK volume or uniformly at random [default: fdk]"),
        click.Option(["--seed", "seed"], type=Seed(), default=None, help="random seed [default: 0]"),
        click.Option(["--backend", "backend"], type=click.Choice(["cl", "torch"]), default=None,
                     help="OpenCL kernels or the plain torch reference [default: cl]"),
        click.Option(["--projector", "projector_mode"], type=click.Choice(["affine", "exact"]), default=None,
                     help="R2-Gaussian's affine splat or the exact ray integral [default: affine]"),
        click.Option(["--scale-floor", "scale_floor"], type=FiniteFloat(min=0), default=None,
                     help="smallest Gaussian scale as a fraction of the scan's resolution (voxel or detector "
                          "pixel at the axis); 0 keeps only R2-Gaussian's 0.05 % of the volume [default: 0.4]"),
        click.Option(["--tv", "lambda_tv"], type=FiniteFloat(min=0), default=None,
                     help="weight of the TV term (0 disables it) [default: 0.05]"),
        click.Option(["--dssim", "lambda_dssim"], type=FiniteFloat(min=0), default=None,
                     help="weight of the D-SSIM term [default: 0.25]"),
        click.Option(["--log-every", "log_every"], type=click.IntRange(min=0), default=None,
                     help="evaluate and log every N iterations [default: 500]"),
        click.Option(["--checkpoint-every", "checkpoint_every"], type=click.IntRange(min=0), default=None,
                     help="write a checkpoint every N iterations (0: only at the end / on Ctrl-C) [default: 1000]"),
        click.Option(["--progress/--no-progress", "progress"], default=None, help="show a progress bar"),
    ]


def _method():
    from clgs.methods import Method

    return Method("r2gs", run_method, options=click_options, atomic_dir=False,
                  help="R2-Gaussian: radiative Gaussian splatting (slow, best at few views)")


METHOD = _method()
