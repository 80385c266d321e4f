"""A smooth deformation beyond a shape model's span: a coarse cubic B-spline displacement.

A shape model with a few modes moves a bone only within its population's shapes; a femur from
another cohort (another neck-shaft angle, a bowed shaft, a local bump) lies partly outside that
span. The residual ``r(theta)`` is a displacement (mm, components x, y, z) on the template's
frame, from a coarse grid of cubic B-spline coefficients ``theta`` (3, nz, ny, nx) with the same
spacing along every axis; it is added to the model's displacement at the template positions,
``p = c + s (p_ref + u(alpha)(p_ref) + r(theta)(p_ref) - c)``
(:class:`clgs.shape.gaussian_set.ShapeGuidedSet`).

The residual is evaluated on the shape model's own grid (``field``), where the model's
displacement lives too: the Gaussians' centres, the inverse map and the written surface then
sample ``u + r`` with one trilinear pass. The B-spline is separable, so the field is three small
matrix products; its second derivatives come from the basis's own derivatives, exactly.

Its prior (:meth:`ResidualGrid.prior`): ``mean |r|^2 + bending h^4 mean |D^2 r|^2`` over the model
grid (mm^2; ``h`` the control spacing), the magnitude keeping ``r`` at 0 where no projection
speaks, the bending energy (the thin-plate energy's sum of squared second derivatives, mixed terms
twice) keeping it smooth where one does."""
from __future__ import annotations

import math

import numpy as np
import torch

from clgs.errors import InputError
from clgs.shape.template import zyx_triple


def bspline3(x: np.ndarray, order: int = 0) -> np.ndarray:
    """The uniform cubic B-spline kernel (support (-2, 2)) or its ``order``-th derivative (1, 2)."""
    a = np.abs(x)
    s = np.sign(x)
    inner, outer = a < 1.0, (a >= 1.0) & (a < 2.0)
    if order == 0:
        return np.where(inner, 2.0 / 3.0 - a * a + 0.5 * a ** 3, np.where(outer, (2.0 - a) ** 3 / 6.0, 0.0))
    if order == 1:
        return np.where(inner, s * (-2.0 * a + 1.5 * a * a), np.where(outer, -s * (2.0 - a) ** 2 / 2.0, 0.0))
    if order == 2:
        return np.where(inner, -2.0 + 3.0 * a, np.where(outer, 2.0 - a, 0.0))
    raise InputError(f"B-spline derivative order must be 0, 1 or 2, got {order}")


def control_layout(shape, spacing, points: int) -> tuple:
    """(control points per axis (Z, Y, X), control spacing h in mm, offsets (Z, Y, X) in mm of the
    first control point from the grid's first voxel): ``points`` along the grid's longest side
    (covering it with one control point beyond each end, the cubic's support), the same ``h``
    along the others, each centred on the grid."""
    if int(points) < 4:
        raise InputError(f"the residual needs at least 4 control points along the longest side, got {points}")
    ext = [(n - 1) * d for n, d in zip(shape, zyx_triple("spacing", spacing))]
    h = max(ext) / (int(points) - 3)
    counts, offsets = [], []
    for e in ext:
        n = int(math.ceil(e / h - 1e-9)) + 3
        counts.append(n)
        offsets.append(e / 2.0 - (n - 1) / 2.0 * h)
    return tuple(counts), float(h), tuple(offsets)


class ResidualGrid:
    """Cubic B-spline displacements on a shape model's grid (``shape`` (Z, Y, X), ``spacing``).

    ``points``: control points along the grid's longest side (see :func:`control_layout`)."""

    def __init__(self, shape, spacing, points: int = 12, dtype=torch.float32):
        self.shape = tuple(int(n) for n in shape)
        self.spacing = zyx_triple("spacing", spacing)
        self.points = int(points)
        self.n_control, self.h, offsets = control_layout(self.shape, self.spacing, self.points)
        self.dtype = dtype
        self._grams = {}  # (derivative orders, dtype) -> per-axis Gram matrices of the bases
        # per axis (Z, Y, X): basis (grid points x control points) and its 1st and 2nd derivatives (mm^-k)
        self._basis = []
        for n, d, nc, off in zip(self.shape, self.spacing, self.n_control, offsets):
            t = (np.arange(n) * d - off) / self.h
            x = t[:, None] - np.arange(nc)[None, :]
            self._basis.append([torch.as_tensor(bspline3(x, k) / self.h ** k, dtype=dtype) for k in range(3)])

    @property
    def coefficient_shape(self) -> tuple:
        return (3,) + self.n_control

    def zeros(self) -> torch.Tensor:
        return torch.zeros(self.coefficient_shape, dtype=self.dtype)

    def to(self, dtype) -> ResidualGrid:
        return ResidualGrid(self.shape, self.spacing, self.points, dtype=dtype)

    def _check(self, theta: torch.Tensor) -> torch.Tensor:
        if tuple(theta.shape) != self.coefficient_shape:
            raise InputError(f"residual coefficients must be {self.coefficient_shape}, got {tuple(theta.shape)}")
        return theta

    def _apply(self, theta, kz=0, ky=0, kx=0) -> torch.Tensor:
        bz, by, bx = self._basis[0][kz], self._basis[1][ky], self._basis[2][kx]
        bz, by, bx = (b.to(theta.dtype) for b in (bz, by, bx))
        # one axis at a time (a single four-operand einsum may form the outer product of the bases)
        out = torch.matmul(theta, bx.T)  # (3, nz, ny, X)
        out = torch.matmul(by, out)  # (3, nz, Y, X)
        return torch.matmul(bz, out.reshape(3, bz.shape[1], -1)).reshape(3, bz.shape[0], by.shape[0], bx.shape[0])

    def field(self, theta: torch.Tensor) -> torch.Tensor:
        """r (3, Z, Y, X) mm on the model grid; differentiable in ``theta``."""
        return self._apply(self._check(theta))

    def _mean_square(self, theta, kz=0, ky=0, kx=0) -> torch.Tensor:
        """mean over the grid of |the (kz, ky, kx) derivative of r|^2, from the bases' Gram matrices
        (``theta^T (Gz x Gy x Gx) theta / N``: the same value as on the grid, at the control grid's cost)."""
        key = (kz, ky, kx, theta.dtype)
        grams = self._grams.get(key)
        if grams is None:
            grams = [(b[k].T @ b[k]).to(theta.dtype) for b, k in zip(self._basis, (kz, ky, kx))]
            self._grams[key] = grams
        gz, gy, gx = grams
        out = torch.matmul(theta, gx)  # Gram matrices are symmetric
        out = torch.matmul(gy, out)
        out = torch.matmul(gz, out.reshape(3, gz.shape[0], -1)).reshape(theta.shape)
        return (theta * out).sum() / float(np.prod(self.shape))

    def bending(self, theta: torch.Tensor) -> torch.Tensor:
        """mean over the grid of the summed squared second derivatives of r (mm^-2), mixed terms twice."""
        self._check(theta)
        out = 0.0
        for kz, ky, kx, w in ((2, 0, 0, 1), (0, 2, 0, 1), (0, 0, 2, 1), (1, 1, 0, 2), (1, 0, 1, 2), (0, 1, 1, 2)):
            out = out + w * self._mean_square(theta, kz, ky, kx)
        return out

    def prior(self, theta: torch.Tensor, bending: float) -> torch.Tensor:
        """``mean |r|^2 + bending h^4 mean |D^2 r|^2`` (mm^2) over the model grid."""
        value = self._mean_square(self._check(theta))
        if bending > 0:
            value = value + float(bending) * self.h ** 4 * self.bending(theta)
        return value

    def describe(self) -> dict:
        return {"control_points": list(self.n_control), "control_spacing_mm": round(self.h, 4), "points": self.points}
