"""Assembling a Gaussian fit: the volume box and scale bounds of a scan, the FDK start and the
value normalisation (training units, see :mod:`clgs.methods.r2gs`), the image and TV loss terms,
and the trainer with its densifier, evaluator and checkpoints."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from clgs.ct.fdk import fdk
from clgs.errors import InputError
from clgs.fit import losses as L
from clgs.fit import tv_patch
from clgs.fit.config import CHECKPOINT
from clgs.fit.gaussians import Densifier
from clgs.fit.outputs import make_evaluator
from clgs.fit.schedule import coarse_hook, plateau_hook
from clgs.fit.trainer import Backend, LossTerm, Trainer


def volume_box(geometry) -> tuple:
    """Half-extents (x, y, z) of the reconstruction volume in scene units."""
    return tuple(0.5 * geometry.sVoxel[::-1] * geometry.scale)


def scale_bounds_for(geometry, scale_bounds, scale_floor):
    """The scale bounds (fractions of the volume extent) a scan allows: ``scale_bounds`` with its
    lower end raised to ``scale_floor`` x :attr:`Geometry.resolution_mm` when that is larger.

    Why: with only the extent's 0.05 % as the floor (R2-Gaussian's, one eighth of a voxel on its
    256^3 scans), a 64^3 scan lets Gaussians shrink to 1/30 of a voxel; long runs then fit the
    views' noise with sub-voxel needles that voxel-centre sampling misses, and 3D PSNR falls while
    the projection PSNR still rises (docs/methods.md)."""
    if scale_bounds is None:
        return None
    lo, hi = (float(b) for b in scale_bounds)
    if scale_floor:
        lo = max(lo, float(scale_floor) * geometry.resolution_mm / float(np.max(geometry.sVoxel)))
    if not lo < hi:
        raise InputError(f"the smallest Gaussian scale ({lo:.4g} of the volume, from scale_bounds and scale_floor "
                         f"{scale_floor} x the scan's {geometry.resolution_mm:.3g} mm resolution) is not below the "
                         f"largest ({hi:.4g}); lower scale_floor or raise scale_bounds[1]")
    return lo, hi


def fdk_volume(scan) -> np.ndarray:
    """The start volume of the Gaussian methods: FDK of the scan, circular or per view (for a
    per-view geometry on its own orbit, :mod:`clgs.ct.fdk_views`)."""
    return np.asarray(fdk(scan.projections, scan.geometry), dtype=np.float32)


def value_scale_from(volume: np.ndarray) -> float:
    """``1 / p99.9`` of a volume (its robust maximum); see the module doc."""
    p = float(np.percentile(np.asarray(volume, np.float32), 99.9))
    if not (math.isfinite(p) and p > 0):
        raise InputError(f"the FDK volume's 99.9th percentile is {p}: the projections look empty or "
                         "negative; give value_scale explicitly")
    return 1.0 / p


def tv_term(size: int, every: int = 1):
    """TV of the model voxelised on a random ``size^3`` block of the volume grid, shifted by a random
    fraction of a voxel as R2-Gaussian places its patch anywhere (on the OpenCL
    backend one fused device pass: cull, field, TV and its gradient, see :mod:`clgs.fit.tv_patch`).

    ``every`` > 1: only every ``every``-th iteration, weighted ``every`` times (the same TV per
    iteration on average, for a fraction of the cost: the patch is most of a late iteration of a
    scene of large Gaussians, docs/schedules.md); other iterations skip the term."""
    every = max(int(every), 1)

    def fn(ctx):
        if ctx.iteration % every:
            return None
        grid = ctx.geometry.volume_grid(scene=True)
        block = L.random_block(grid, size, ctx.generator, subvoxel=True)  # off the evaluation lattice
        tv = tv_patch.patch_tv(ctx.trainer.backend, ctx.tensors, block)
        return tv if every == 1 else tv * every

    return fn


def projection_losses(cfg) -> list:
    """R2-Gaussian's terms: L1 + ``lambda_dssim`` D-SSIM on the rendered view (each view of a
    multi-view step, averaged), ``lambda_tv`` TV on a random block of the volume (once a step;
    ``cfg``: a :class:`clgs.fit.config.GaussianFitConfig`)."""
    image = L.ImageTerms(dssim=cfg.lambda_dssim > 0)  # L1 and D-SSIM from one pass on the OpenCL backend
    return [
        LossTerm("l1", 1.0, image.l1, per_view=True),
        LossTerm("dssim", cfg.lambda_dssim, image.dssim, per_view=True),
        LossTerm("tv", cfg.lambda_tv, tv_term(cfg.tv_size, cfg.tv_every)),
    ]


def make_trainer(scan, cfg, sets, losses, out_dir=None, progress=False) -> Trainer:
    """The trainer of a Gaussian method: training-unit projections, the densifier (it edits only
    sets marked ``densify``), the plateau rule when the schedule has one, the evaluator and
    checkpoints in ``out_dir``. ``cfg`` holds the
    shared settings (R2GSConfig's names); ``cfg.value_scale`` must be set."""
    geo = scan.geometry
    densifier = Densifier(geo, start=cfg.densify_start, until=cfg.densify_until, interval=cfg.densify_interval,
                          grad_threshold=cfg.grad_threshold, scale_threshold=cfg.densify_scale_threshold,
                          min_density=cfg.min_density, max_gaussians=cfg.max_gaussians)
    projections = np.asarray(scan.projections, np.float32) * np.float32(geo.scale * cfg.value_scale)
    out_dir = None if out_dir is None else Path(out_dir)
    plateau = plateau_hook(cfg)  # the fast schedule's stopping rule (None: every iteration runs)
    trainer = Trainer(
        sets, geo, projections, losses, iterations=cfg.iterations,
        backend=Backend(cfg.backend, cfg.projector_mode), render_scale=geo.scale, seed=cfg.seed,
        hooks=[densifier] + ([plateau] if plateau is not None else []),
        evaluate=make_evaluator(scan, cfg.value_scale), log_every=cfg.log_every,
        log_early=cfg.log_early, checkpoint_every=cfg.checkpoint_every if out_dir is not None else 0,
        checkpoint_path=None if out_dir is None else out_dir / CHECKPOINT, progress=progress,
        config=cfg.to_json(), views_per_step=cfg.views_per_step,
    )
    coarse = coarse_hook(trainer, cfg)  # early iterations on a binned detector, when asked for
    if coarse is not None:
        trainer.hooks.insert(0, coarse)
    return trainer


def restore(trainer: Trainer, state, cfg) -> None:
    """Load a checkpoint into a freshly built trainer (no-op without one)."""
    if state is not None:
        trainer.load_state_dict(state)
        trainer.iterations = trainer.config["iterations"] = cfg.iterations
