"""Plain torch reference of the voxelizer (``cl/voxelizer.cl``), for tests and benchmarks.

Same field and the same cut as the kernels: Gaussian i contributes
``rho_i exp(-d^T P_i d / 2)``, ``d = x - p_i``, only where ``-e_i <= d <= e_i`` on every axis
(``e_i`` its 3-sigma half-widths, ``clgs.reference.gaussians.axis_extent``), with ``d`` computed in the
input dtype exactly as the kernels compute it; autograd gives the gradients.

``field_at_points``/``voxelize``/``voxelize_points`` are dense over (points x Gaussians): slow but
obviously right. ``voxelize_windowed`` (grids) and ``voxelize_points_kdtree`` (points) do work
proportional to the Gaussians' boxes, as one would write them for speed with torch and scipy
(the benchmarks' baselines).
"""
from __future__ import annotations

import numpy as np
import torch

from clgs.reference.gaussians import axis_extent, precision


def field_at_points(means, prec, densities, extent, points, chunk: int = 1 << 22) -> torch.Tensor:
    """Field at ``points`` (M, 3) from packed precisions ``prec`` (N, 6) and half-widths ``extent``
    (N, 3): (M,). Differentiable wrt means, prec and densities."""
    m, n = points.shape[0], means.shape[0]
    out = []
    step = max(1, chunk // max(n, 1))
    pxx, pxy, pxz, pyy, pyz, pzz = prec.unbind(-1)
    for s in range(0, m, step):
        d = points[s:s + step, None, :] - means[None, :, :]  # (m, N, 3)
        inside = ((d >= -extent) & (d <= extent)).all(-1)
        dx, dy, dz = d.unbind(-1)
        q = (pxx * dx * dx + pyy * dy * dy + pzz * dz * dz
             + 2 * (pxy * dx * dy + pxz * dx * dz + pyz * dy * dz))
        w = torch.where(inside, densities * torch.exp(-0.5 * torch.where(inside, q, torch.zeros_like(q))),
                        torch.zeros_like(q))
        out.append(w.sum(1))
    return torch.cat(out) if out else means.new_zeros(0)


def grid_points(grid, dtype=torch.float32) -> torch.Tensor:
    """(Z, Y, X, 3) sample points of a ``Grid``: coordinates formed in float64, rounded to dtype."""
    pts = np.stack(np.meshgrid(
        *[(np.float64(grid.origin[a]) + np.float64(grid.spacing[a]) * np.arange(grid.shape[2 - a]))
          for a in (2, 1, 0)], indexing="ij")[::-1], -1)
    return torch.from_numpy(pts).to(dtype)


def voxelize(means, scales, quats, densities, grid) -> torch.Tensor:
    """Reference of ``clgs.ops.voxelizer.voxelize``: (Z, Y, X)."""
    prec = precision(scales, quats)
    extent = axis_extent(scales, quats).to(means.dtype)
    pts = grid_points(grid, means.dtype)
    return field_at_points(means, prec, densities, extent, pts.reshape(-1, 3)).reshape(pts.shape[:3])


def voxelize_points(means, scales, quats, densities, points) -> torch.Tensor:
    """Reference of ``clgs.ops.voxelizer.voxelize_points``: (M,)."""
    prec = precision(scales, quats)
    extent = axis_extent(scales, quats).to(means.dtype)
    return field_at_points(means, prec, densities, extent, torch.as_tensor(points, dtype=means.dtype))


def _grid_axes(grid, dtype):
    return [torch.from_numpy(np.float64(grid.origin[a]) + np.float64(grid.spacing[a]) * np.arange(grid.shape[2 - a]))
            .to(dtype) for a in range(3)]


def voxelize_windowed(means, scales, quats, densities, grid, chunk: int = 2048) -> torch.Tensor:
    """Same as ``voxelize`` with work proportional to the Gaussians' boxes: each Gaussian whose box
    meets the grid is evaluated on a window of samples as large as the largest box, masked by its
    own box, and scatter-added (``index_add``) into the grid."""
    dtype = means.dtype
    prec = precision(scales, quats)
    extent = axis_extent(scales, quats).to(dtype)
    nz, ny, nx = grid.shape
    sizes = (nx, ny, nz)
    axes = _grid_axes(grid, dtype)
    origin = torch.tensor(grid.origin, dtype=torch.float64)
    spacing = torch.tensor(grid.spacing, dtype=torch.float64)
    with torch.no_grad():
        lo = torch.floor((means.detach().double() - extent.double() - origin) / spacing).long() - 1
        hi = torch.floor((means.detach().double() + extent.double() - origin) / spacing).long() + 1
        dims = torch.tensor(sizes)
        keep = ((hi >= 0) & (lo < dims)).all(1).nonzero().reshape(-1)
        width = (hi - lo + 1)[keep].amax(0) if keep.numel() else torch.ones(3, dtype=torch.long)
    out = means.new_zeros(nz * ny * nx)
    for s in range(0, keep.numel(), chunk):
        sel = keep[s:s + chunk]
        p, e, rho, pr = means[sel], extent[sel], densities[sel], prec[sel]
        idx, d, ok = [], [], []
        for a in range(3):
            i = lo[sel, a:a + 1] + torch.arange(int(width[a]))  # (n, K_a)
            valid = (i >= 0) & (i < sizes[a])
            i = i.clamp(0, sizes[a] - 1)
            da = axes[a][i] - p[:, a:a + 1]
            idx.append(i)
            d.append(da)
            ok.append(valid & (da >= -e[:, a:a + 1]) & (da <= e[:, a:a + 1]))
        dx, dy, dz = d[0][:, None, None, :], d[1][:, None, :, None], d[2][:, :, None, None]
        c = [pr[:, k, None, None, None] for k in range(6)]
        q = c[0] * dx * dx + c[3] * dy * dy + c[5] * dz * dz + 2 * (c[1] * dx * dy + c[2] * dx * dz + c[4] * dy * dz)
        inside = ok[0][:, None, None, :] & ok[1][:, None, :, None] & ok[2][:, :, None, None]
        flat = (idx[2][:, :, None, None] * ny + idx[1][:, None, :, None]) * nx + idx[0][:, None, None, :]
        w = rho[:, None, None, None] * torch.exp(-0.5 * q)
        out = out.index_add(0, flat[inside], w[inside])
    return out.reshape(nz, ny, nx)


def voxelize_points_kdtree(means, scales, quats, densities, points) -> torch.Tensor:
    """Same as ``voxelize_points``, evaluating only (Gaussian, point) pairs found by a scipy KD-tree
    ball query around each Gaussian (radius: its box's half-diagonal), scatter-added."""
    from scipy.spatial import cKDTree

    dtype = means.dtype
    points = torch.as_tensor(points, dtype=dtype)
    prec = precision(scales, quats)
    extent = axis_extent(scales, quats).to(dtype)
    out = means.new_zeros(points.shape[0])
    if means.shape[0] == 0 or points.shape[0] == 0:
        return out
    tree = cKDTree(points.detach().double().numpy())
    radius = extent.detach().double().norm(dim=1).numpy() * (1 + 1e-6) + 1e-12
    hits = tree.query_ball_point(means.detach().double().numpy(), radius)
    counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
    if counts.sum() == 0:
        return out
    gi = torch.from_numpy(np.repeat(np.arange(len(hits)), counts))
    pj = torch.from_numpy(np.concatenate([np.asarray(h, np.int64) for h in hits if h]))
    d = points[pj] - means[gi]
    e = extent[gi]
    inside = ((d >= -e) & (d <= e)).all(1)
    gi, pj, d = gi[inside], pj[inside], d[inside]
    pr = prec[gi]
    dx, dy, dz = d.unbind(-1)
    q = (pr[:, 0] * dx * dx + pr[:, 3] * dy * dy + pr[:, 5] * dz * dz
         + 2 * (pr[:, 1] * dx * dy + pr[:, 2] * dx * dz + pr[:, 4] * dy * dz))
    return out.index_add(0, pj, densities[gi] * torch.exp(-0.5 * q))
