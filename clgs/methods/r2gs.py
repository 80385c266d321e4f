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
from it bit for bit). The method knows no anatomy, so it writes no bone surface itself: the
commands add ``surface.stl`` at a bone level they can name (docs/outputs.md).

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

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clgs.errors import InputError
from clgs.fit.assembly import (
    fdk_volume,
    make_trainer,
    projection_losses,
    restore,
    scale_bounds_for,
    value_scale_from,
    volume_box,
)
from clgs.fit.config import CHECKPOINT, GaussianFitConfig, run_config, run_folder, setting
from clgs.fit.estimate import run_clock
from clgs.fit.gaussians import GaussianSet, init_from_volume, init_random, r2gs_schedules
from clgs.fit.outputs import gaussians_in_scan_units, voxelize_volume, write_outputs
from clgs.fit.trainer import Trainer
from clgs.fit.training_log import TrainingLog
from clgs.io.scan import Scan
from clgs.methods import Method
from clgs.methods.gaussian import RUN_OPTIONS, method_output
from clgs.progress import enabled, phase


@dataclass
class R2GSConfig(GaussianFitConfig):
    """R2-Gaussian's defaults (iterations, initialisation, loss weights, densification)."""

    # initial count (fewer when fewer voxels pass the threshold)
    n_gaussians: int = setting(50_000, "--gaussians",
                               "initial number of Gaussians")
    init: str = setting("fdk", "--init",
                        "initialise from an FDK volume, from OS-SART (--set init_sart_iterations=N, 5 subsets), or "
                        "uniformly at random")  # "fdk" | "sart" | "random"
    init_sart_iterations: int = 10  # OS-SART iterations of the "sart" start (5 subsets)

    CLI = ("iterations", "schedule", "n_gaussians", "max_gaussians", "init", "seed", "backend", "projector_mode",
           "scale_floor", "lambda_tv", "lambda_dssim", "views_per_step", "log_every", "log_early", "checkpoint_every")
    KIND = "r2gs"
    FAST_ITERATIONS = 10_000  # the fast schedule's run (clgs.fit.schedule; docs/schedules.md)
    # on 20 views or more: four views a step at twice the learning rates, 6 000 steps (the thorax,
    # 25 views: the paper's 30 000-iteration 3D PSNR in about 0.4 of its time, where one view a
    # step needs two thirds of it, docs/schedules.md); sparse scans keep R2-Gaussian's one view a
    # step (every femur table was made so)
    FAST_MANY_VIEWS = {"views_per_step": 4, "lr_factor": 2.0, "iterations": 6_000}
    # no plateau rule by default: on the thorax the projection loss stops setting records at 3 000
    # iterations while the volume gains another 1.4 dB (docs/schedules.md); --set stop_every=500
    FAST_STOP_EVERY = 0
    CHOICES = {**GaussianFitConfig.CHOICES, "init": ("fdk", "sart", "random")}
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



# ---------------------------------------------------------------------- the method
def build_trainer(scan, cfg: R2GSConfig, out_dir=None, *, progress=False, fdk=None, state=None,
                  gaussians=None) -> Trainer:
    """Everything but the loop: normalisation, initial Gaussians, losses, densifier, trainer.

    ``state`` (a loaded checkpoint) skips the initialisation; the checkpoint then overwrites it.
    ``gaussians``: initial (means, scales, quats, densities) in training units, instead of ``cfg.init``.
    """
    geo = scan.geometry
    box = volume_box(geo)
    sched = r2gs_schedules(cfg.schedule_iterations or cfg.iterations, cfg.lr_factor)
    kw = dict(box=box, scale_bounds=scale_bounds_for(geo, cfg.scale_bounds, cfg.scale_floor), schedules=sched,
              name="free", densify=True)
    if cfg.init == "sart" and gaussians is None and state is None and fdk is None:
        fdk = sart_start(scan, cfg.init_sart_iterations)
    if cfg.value_scale is None:
        fdk = fdk_volume(scan) if fdk is None else fdk
        cfg.value_scale = value_scale_from(fdk)
    if gaussians is not None:
        gset = GaussianSet(*(np.asarray(a, np.float32) for a in gaussians), **kw)
    elif state is not None:
        empty = np.zeros((0, 3), np.float32)
        gset = GaussianSet(empty, empty, np.zeros((0, 4), np.float32), np.zeros(0, np.float32), raw=True, **kw)
    elif cfg.init in ("fdk", "sart"):
        fdk = fdk_volume(scan) if fdk is None else fdk
        with phase(f"placing {cfg.n_gaussians} Gaussians on the {'OS-SART' if cfg.init == 'sart' else 'FDK'} volume"):
            gset = init_from_volume(fdk * cfg.value_scale, geo.volume_grid(scene=True), n_gaussians=cfg.n_gaussians,
                                    threshold=cfg.init_threshold, density_factor=cfg.density_factor, seed=cfg.seed,
                                    **kw)
    elif cfg.init == "random":
        gset = init_random(cfg.n_gaussians, seed=cfg.seed, **kw)
    else:
        raise InputError(f"init must be 'fdk', 'sart' or 'random', got {cfg.init!r}")
    return make_trainer(scan, cfg, [gset], projection_losses(cfg), out_dir, progress)


def sart_start(scan, iterations: int) -> np.ndarray:
    """The OS-SART start volume (``iterations`` iterations, 5 subsets, non-negative): a better
    start than FDK at few views, bought for seconds (docs/schedules.md)."""
    from clgs.ct.sart import sart

    with phase(f"the OS-SART start ({iterations} iterations)"):
        return np.asarray(sart(scan.projections, scan.geometry, n_iter=int(iterations),
                               subsets=min(5, scan.geometry.n_views)), np.float32)


def reconstruct_r2gs(scan, out_dir=None, iterations: int | None = None, *, resume: bool = False,
                     overwrite: bool = False, progress: bool = True, fdk=None, **settings) -> R2GSResult:
    """Reconstruct ``scan`` (a :class:`clgs.io.scan.Scan` or a scan folder) with R2-Gaussian.

    ``settings`` are :class:`R2GSConfig` fields (``backend``, ``seed``, ``lambda_tv``, ...).
    ``out_dir`` gets the outputs and checkpoints (none without it); one that holds anything is
    refused unless ``resume=True`` (continue its run from its checkpoint, with the checkpoint's
    settings, to the iterations it was started with, or to ``iterations`` when given) or
    ``overwrite=True`` (its clgs files are removed first): :func:`clgs.fit.config.run_folder`.
    ``iterations=None`` on a new run: the schedule's length (``schedule="fast"``, the default:
    the paper's schedule cut at 10 000, or on 20 views or more 6 000 steps of four views at twice
    the learning rates; ``"paper"``: R2-Gaussian's 30 000; docs/schedules.md).
    ``fdk``: a ready FDK volume (else computed). Ctrl-C stops cleanly: outputs so far are written
    and ``result.interrupted`` is True.
    """
    with run_folder(out_dir, resume, overwrite), enabled(progress), run_clock():
        return _reconstruct_r2gs(scan, out_dir, iterations, resume=resume, progress=progress, fdk=fdk, **settings)


def _reconstruct_r2gs(scan, out_dir=None, iterations: int | None = None, *, resume: bool = False,
                      progress: bool = True, fdk=None, **settings) -> R2GSResult:
    """:func:`reconstruct_r2gs` in a run folder already claimed."""
    if not isinstance(scan, Scan):
        scan = Scan.load(scan)
    cfg, state = run_config(R2GSConfig, iterations, settings, resume, out_dir, n_views=scan.geometry.n_views)
    trainer = build_trainer(scan, cfg, out_dir, progress=progress, fdk=fdk, state=state)
    restore(trainer, state, cfg)
    trainer.fit()
    with phase("the volume" + (" and the run's files" if out_dir is not None else "")):
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
    result = reconstruct_r2gs(scan, out_dir, iterations, resume=resume, progress=progress, **settings)
    return method_output(result, out_dir, {k: str(v) for k, v in result.files.items()})


METHOD = Method("r2gs", run_method, options=RUN_OPTIONS, config=R2GSConfig, atomic_dir=False,
                help="R2-Gaussian: radiative Gaussian splatting (slow, best at few views)")
