"""What a Gaussian fit reports and leaves behind: figures for the log during training, the model
voxelised on the scan's grid, its Gaussians in the scan's units, and the run folder's files."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from clgs import metrics
from clgs.fit.trainer import Trainer
from clgs.io import atomic
from clgs.io.volume import save_volume


def rendered_views(trainer: Trainer, tensors=None, chunk: int = 8):
    """(model's projections, measured ones) of every training view, training units, in chunks of
    ``chunk`` views (no gradients): what the log's projection PSNR and the plateau rule
    (:func:`clgs.fit.schedule.views_loss`) compare."""
    tensors = tensors or tuple(t.detach() for t in trainer.scene_tensors())
    views = trainer.views
    with torch.no_grad():
        for i in range(0, len(views), chunk):
            part = views[i:i + chunk]
            yield trainer.backend.project(*tensors, trainer.geometry, part) * trainer.render_scale, \
                trainer.projections[part]


def make_evaluator(scan, value_scale: float):
    """Figures for the log: projection PSNR over the training views (peak = the largest measured
    value) and, with a ground truth, 3D PSNR / SSIM of the voxelised volume (clgs.metrics)."""
    truth = None if scan.truth is None else np.asarray(scan.truth, np.float32)

    def evaluate(trainer: Trainer) -> dict:
        tensors = tuple(t.detach() for t in trainer.scene_tensors())
        out = {}
        mse, peak = 0.0, 0.0
        for pred, target in rendered_views(trainer, tensors):
            mse += float(((pred - target) ** 2).sum())
            peak = max(peak, float(target.max()))
        mse /= len(trainer.views) * trainer.projections[0].numel()
        out["proj_psnr"] = 10 * math.log10(peak * peak / mse) if mse > 0 and peak > 0 else float("inf")
        if truth is not None:
            vol = voxelize_volume(trainer, tensors) / value_scale
            figures = metrics.volume_figures(vol, truth)  # None where the truth leaves them undefined
            out.update({k: v for k, v in figures.items() if k in ("psnr3d", "ssim3d") and v is not None})
        return out

    return evaluate


def voxelize_volume(trainer: Trainer, tensors=None) -> np.ndarray:
    """The whole model on the reconstruction grid, training units, (Z, Y, X) float32."""
    with torch.no_grad():
        tensors = tensors or tuple(t.detach() for t in trainer.scene_tensors())
        vol = trainer.backend.voxelize(*tensors, trainer.geometry.volume_grid(scene=True))
    return vol.numpy().astype(np.float32)


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


def write_outputs(trainer: Trainer, out_dir, value_scale: float, volume=None, method: str = "R2-Gaussian") -> dict:
    """Volume (NIfTI), Gaussians (npz), log (CSV + PNG titled by ``method``, the run's method),
    summary; each file atomically."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    volume = voxelize_volume(trainer) / np.float32(value_scale) if volume is None else volume
    paths = {
        "volume": save_volume(out_dir / "volume.nii.gz", volume, trainer.geometry, units="1/mm"),
        "gaussians": atomic.save_npz(out_dir / "gaussians.npz", **gaussians_in_scan_units(trainer, value_scale)),
        "log": trainer.log.write_csv(out_dir / "log.csv"),
        "config": atomic.write_json(out_dir / "config.json", trainer.config),
        "summary": atomic.write_text(out_dir / "summary.txt", trainer.log.summary() + "\n"),
    }
    if trainer.log.rows:
        paths["plot"] = trainer.log.plot(out_dir / "log.png", title=f"{method}: {trainer.iteration} iterations")
    return paths
