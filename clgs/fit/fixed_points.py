"""Trilinear sampling at points that never move, as a sparse matrix built once.

The shape-guided set samples its displacement field at the Gaussians' template positions every
iteration, forward and backward; those positions are fixed, so the eight corner indices and
weights of each point are too. ``W`` (points x voxels, eight entries a row) and its transpose,
kept in CSR form, make the forward ``W u`` and the gradient wrt the field ``W^T g`` two sparse
products: the same values as torch's ``grid_sample(mode="bilinear", padding_mode="border",
align_corners=True)`` to rounding (the weights are formed in float64, then cast), without
recomputing the weights or the unneeded gradient wrt the points, and in a fixed order (the same
input gives the same bits). Side by side: ``clgs bench train --method shape --alternate``."""
from __future__ import annotations

import warnings

import numpy as np
import torch

from clgs.errors import InputError


class FixedPointSampler:
    """Samples (N, C) of (C, Z, Y, X) fields at the fixed ``points`` (N, 3) in voxel units (x, y,
    z; voxel [k, j, i] at x = i, y = j, z = k); clamped to the border outside the grid.
    Differentiable in the field."""

    def __init__(self, points, shape, dtype=torch.float32):
        pts = np.asarray(points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points,
                         np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"points must be (N, 3), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise InputError("points contain NaN or Inf")
        Z, Y, X = (int(n) for n in shape)
        if min(Z, Y, X) < 2:
            raise InputError(f"a field grid needs at least 2 voxels per axis, got {tuple(shape)}")
        self.shape = (Z, Y, X)
        self.dtype = dtype
        n = pts.shape[0]
        lo, frac = [], []
        for a, size in enumerate((X, Y, Z)):
            c = np.clip(pts[:, a], 0.0, size - 1.0)
            i0 = np.minimum(np.floor(c), size - 2).astype(np.int64)
            lo.append(i0)
            frac.append(c - i0)
        (ix, iy, iz), (fx, fy, fz) = lo, frac
        base = (iz * Y + iy) * X + ix
        cols, vals = [], []
        for corner in range(8):
            dx, dy, dz = corner & 1, (corner >> 1) & 1, (corner >> 2) & 1
            cols.append(base + dx + dy * X + dz * X * Y)
            vals.append((fx if dx else 1 - fx) * (fy if dy else 1 - fy) * (fz if dz else 1 - fz))
        rows = np.repeat(np.arange(n, dtype=np.int64), 8)
        cols = np.stack(cols, 1).reshape(-1)
        vals = np.stack(vals, 1).reshape(-1)
        n_vox = Z * Y * X
        self.W = _csr(rows, cols, vals, (n, n_vox), dtype)
        self.WT = _csr(cols, rows, vals, (n_vox, n), dtype)

    def __len__(self):
        return self.W.shape[0]

    def __call__(self, field: torch.Tensor) -> torch.Tensor:
        if field.dim() != 4 or tuple(field.shape[1:]) != self.shape:
            raise InputError(f"field must be (C, {', '.join(map(str, self.shape))}), got {tuple(field.shape)}")
        if field.dtype != self.dtype:
            raise InputError(f"field must be {self.dtype}, got {field.dtype}")
        return _Apply.apply(field, self)


def _csr(rows, cols, vals, size, dtype):
    """A CSR matrix from (row, col, value) triples, entries of each row in column order."""
    order = np.lexsort((cols, rows))
    rows, cols, vals = rows[order], cols[order], vals[order]
    crow = np.zeros(size[0] + 1, np.int64)
    np.cumsum(np.bincount(rows, minlength=size[0]), out=crow[1:])
    with warnings.catch_warnings():  # torch calls its CSR support beta; the tests pin what is used
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(torch.from_numpy(crow), torch.from_numpy(cols),
                                       torch.from_numpy(vals).to(dtype), size=size, check_invariants=False)


class _Apply(torch.autograd.Function):
    @staticmethod
    def forward(ctx, field, sampler):
        ctx.sampler = sampler
        C = field.shape[0]
        return sampler.W @ field.detach().reshape(C, -1).T.contiguous()

    @staticmethod
    def backward(ctx, grad):
        s = ctx.sampler
        g = s.WT @ grad.contiguous()
        return g.T.reshape(grad.shape[1], *s.shape), None
