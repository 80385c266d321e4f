"""From a Gaussian's scale and rotation to the symmetric matrices the kernels consume (torch).

Kernels never see scales and quaternions: they take a covariance or a precision (inverse
covariance) packed as 6 numbers ``(xx, xy, xz, yy, yz, zz)``, and return gradients to those
6 numbers. Torch carries the chain rule back to scale and rotation, so the kernels stay small
and every parameterisation (bounded or exp scales, any rotation) differentiates for free.

The precision is built as ``R diag(1/s^2) R^T`` directly (never by inverting a covariance), so
needle-thin Gaussians (scale ratios of 1e-3 and beyond) keep full accuracy in float32.

These are the plain torch definitions (the tests' reference). Training uses
``clgs.ops.voxelizer.cov_prec``: the same three results from one OpenCL kernel, with a closed-form
backward kernel (on a CPU ~20x cheaper than element-wise torch for 50k Gaussians).
"""
from __future__ import annotations

import torch

SYM6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def quaternion_to_rotation(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) rotation matrices."""
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    q = q / torch.clamp(norm, min=torch.finfo(q.dtype).tiny ** 0.5)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(q.shape[:-1] + (3, 3))


def pack_sym(m: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) symmetric -> (N, 6) as (xx, xy, xz, yy, yz, zz)."""
    return torch.stack([m[..., i, j] for i, j in SYM6], -1)


def unpack_sym(v: torch.Tensor) -> torch.Tensor:
    """(N, 6) -> (N, 3, 3) symmetric."""
    xx, xy, xz, yy, yz, zz = v.unbind(-1)
    return torch.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], -1).reshape(v.shape[:-1] + (3, 3))


def covariance(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """(N, 6) covariance ``R diag(s^2) R^T`` from activated scales (N, 3) and quaternions (N, 4)."""
    r = quaternion_to_rotation(quats)
    return pack_sym((r * (scales * scales).unsqueeze(-2)) @ r.transpose(-1, -2))


def precision(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """(N, 6) precision ``R diag(1/s^2) R^T``, built without a matrix inverse."""
    r = quaternion_to_rotation(quats)
    return pack_sym((r * (1.0 / (scales * scales)).unsqueeze(-2)) @ r.transpose(-1, -2))


def axis_extent(scales: torch.Tensor, quats: torch.Tensor, n_sigma: float = 3.0) -> torch.Tensor:
    """(N, 3) half-widths of the axis-aligned box holding each Gaussian's ``n_sigma`` ellipsoid:
    ``n_sigma * sqrt(diag(covariance))``. Not differentiated (used for binning only)."""
    with torch.no_grad():
        r = quaternion_to_rotation(quats)
        var = ((r * r) * (scales * scales).unsqueeze(-2)).sum(-1)
        return n_sigma * torch.sqrt(var)
