"""The TV patch loss term of R2-Gaussian's loss: total variation of the Gaussian field on a small
block, fused on the OpenCL backend.

``tv_patch(means, prec, densities, extent, grid)`` is ``clgs.fit.losses.tv3d`` of
``clgs.ops.voxelizer.voxelize_precision(means, prec, densities, extent, grid)``, run by the fused
operator :class:`clgs.ops.tv_patch.PatchTV` (culling, field, TV and gradient rows on the device in
one batch of launches with one wait; see that module for why and how exact) on patches, and
through the voxelizer and ``tv3d`` on larger grids.

``patch_tv(backend, tensors, grid)`` is the training loss term's entry: with the OpenCL backend it
reuses the precisions and half-widths that the step's projection built (``Backend._kept``), else
builds them for the Gaussians a ``3 max(scale)`` cube lets reach the block; with the torch
backend it is ``tv3d(backend.voxelize(...))``.
"""
from __future__ import annotations

import numpy as np
import torch

from clgs.errors import InputError
from clgs.fit.losses import tv3d
from clgs.geometry import Grid
from clgs.ops.tv_patch import PatchTV, TVPatchFunction, patch_operator
from clgs.ops.voxelizer import (
    SMALL_CELLS,
    Voxelizer,
    check_grid,
    columns,
    cov_prec,
    default_voxelizer,
    grid_candidates,
    np_dtype,
    voxelize_precision,
)


def _runner(voxelizer: Voxelizer | None) -> PatchTV:
    """The fused operator that runs like ``voxelizer`` (None: the process-wide one)."""
    return patch_operator(voxelizer)


def tv_patch(means, prec, densities, extent, grid: Grid, voxelizer: Voxelizer | None = None) -> torch.Tensor:
    """``tv3d`` of the field on ``grid`` (a block, e.g. ``losses.random_block``) from every Gaussian's
    mean (N, 3), packed precision (N, 6), density (N,) and 3-sigma half-widths (N, 3): a scalar,
    differentiable wrt means, prec and densities. Grids of more than 512 bricks (8^3 samples) go
    through ``voxelize_precision`` and ``tv3d`` (the fused kernels are for patches)."""
    n = means.shape[0] if means.dim() == 2 else -1
    if means.shape != (n, 3) or prec.shape != (n, 6) or densities.shape != (n,) or extent.shape != (n, 3):
        raise InputError(
            "expected means (N, 3), prec (N, 6), densities (N,), extent (N, 3); got "
            f"{tuple(means.shape)}, {tuple(prec.shape)}, {tuple(densities.shape)}, {tuple(extent.shape)}")
    if any(t.dtype != means.dtype for t in (prec, densities, extent)):
        raise TypeError("means, prec, densities and extent must share one dtype (float32 or float64)")
    np_dtype(means.dtype)
    check_grid(grid)
    vox = voxelizer or default_voxelizer()
    _, _, nb = vox.brick_cells(grid)
    if int(np.prod(nb)) > SMALL_CELLS:
        return tv3d(voxelize_precision(means, prec, densities, extent, grid, vox))
    if not (torch.is_grad_enabled() and any(t.requires_grad for t in (means, prec, densities))):
        value = _runner(vox).forward(means, prec, densities, extent, grid)[0]  # no gradient rows
        return means.new_tensor(value)
    return TVPatchFunction.apply(means, prec, densities, extent.detach(), grid, _runner(vox))


def patch_field(means, prec, densities, extent, grid: Grid, voxelizer: Voxelizer | None = None) -> torch.Tensor:
    """The field the fused path voxelises (Z, Y, X), no autograd: for tests and checks."""
    with torch.no_grad():
        return _runner(voxelizer).forward(means, prec, densities, extent, grid, (), field=True)[3]


def patch_tv(backend, tensors, grid: Grid) -> torch.Tensor:
    """The TV loss term on ``grid`` for the scene ``tensors`` = (means, scales, quats, densities):
    ``tv3d(backend.voxelize(*tensors, grid))``, fused on the OpenCL backend (see the module doc)."""
    means, scales, quats, densities = tensors
    if getattr(backend, "name", None) != "cl":
        return tv3d(backend.voxelize(means, scales, quats, densities, grid))
    kept = backend._kept(scales, quats)
    if kept is not None:
        return tv_patch(means, kept[1], densities, kept[2], grid)

    # no matrices from this step's projection: build them only for the Gaussians a 3 max(scale)
    # cube lets reach the block (as Backend._cl_voxelize does)
    idx = grid_candidates(means, columns(scales.detach()).amax(0) * 3.003, grid)
    if idx is not None:
        means, scales, quats, densities = (t.index_select(0, idx) for t in (means, scales, quats, densities))
    _, prec, extent = cov_prec(scales, quats, cov=False, prec=True, extent=True)
    return tv_patch(means, prec, densities, extent, grid)
