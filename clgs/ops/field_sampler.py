"""Trilinear sampling of a field on a regular grid at points, differentiable in both, in OpenCL.

``sample(field, points)``: ``field`` (C, Z, Y, X), C <= 4; ``points`` (3, P) rows x, y, z in voxel
units (voxel ``[k, j, i]`` at x = i, y = j, z = k); returns (C, P). Outside the grid a coordinate
is clamped to the border and its derivative is 0 there: the values and gradients of torch's
``grid_sample(mode="bilinear", padding_mode="border", align_corners=True)`` to rounding (tests
compare them). float32 or float64, by the field's dtype.

Why: the shape-guided method exponentiates its velocity field every iteration, forward and
backward (scaling and squaring: each squaring samples the displacement at displaced grid points),
and torch's CPU 3D ``grid_sample`` is slow at it (docs/kernels.md).

The gradient wrt the field is a gather, not a scatter with atomics: the points are sorted by the
cell they fall in (a stable sort on the host), each cell sums its points' eight corner weights
times the upstream gradient (``sample_cell_sums``), and each voxel adds the sums of the up to eight
cells it is a corner of (``sample_grad_field``). The same input gives the same bits.
"""
from __future__ import annotations

import numpy as np
import torch

from clgs import runtime
from clgs.errors import InputError
from clgs.ops.sorting import stable_order
from clgs.runtime import Operator, round_up

SOURCE = "field_sampler.cl"
MAX_CHANNELS = 4
CELLS_PER_ITEM = 32
GUARD = 16  # spare entries around the cell sums (cl/field_sampler.cl)


class FieldSampler(Operator):
    """Runs ``cl/field_sampler.cl`` (an :class:`~clgs.runtime.Operator`: programs per precision,
    pooled buffers, one call at a time)."""

    SOURCE = SOURCE

    def _program(self, dtype):
        real = runtime.real_name(dtype, "the field")
        return self.variant(real, {"REAL": real, "CELLS_PER_ITEM": CELLS_PER_ITEM})

    @staticmethod
    def _dims(field: np.ndarray):
        C, Z, Y, X = field.shape
        return np.int32(C), np.int32(X), np.int32(Y), np.int32(Z)

    def forward(self, field: np.ndarray, pts: np.ndarray):
        """(values (C, Pp), cells (Pp,) int32) of ``field`` (C, Z, Y, X) at ``pts`` (3, Pp), Pp a
        multiple of 8."""
        C, X, Y, Z = self._dims(field)
        Pp = pts.shape[1]
        out = np.empty((int(C), Pp), field.dtype)
        cells = np.empty(Pp, np.int32)
        with self.call() as io:
            f_buf, p_buf = io.input(field, "field"), io.input(pts, "pts")
            o_buf, c_buf = io.output(out, "out"), io.output(cells, "cells")
            self.launch(self._program(field.dtype), "sample_fwd", (Pp // 8,), None, f_buf, p_buf, o_buf, c_buf,
                        np.int32(Pp), C, X, Y, Z)
            io.fetch([(o_buf, out), (c_buf, cells)])
        return out, cells

    def grad_points(self, field: np.ndarray, pts: np.ndarray, gout: np.ndarray) -> np.ndarray:
        """(3, Pp): the gradient wrt ``pts`` of sum(gout * values); ``gout`` (C, Pp), zero in the pad."""
        C, X, Y, Z = self._dims(field)
        Pp = pts.shape[1]
        gpts = np.empty((3, Pp), field.dtype)
        with self.call() as io:
            bufs = io.input(field, "field"), io.input(pts, "pts"), io.input(gout, "gout")
            g_buf = io.output(gpts, "gpts")
            self.launch(self._program(field.dtype), "sample_grad_pts", (Pp // 8,), None, *bufs, g_buf,
                        np.int32(Pp), C, X, Y, Z)
            io.fetch([(g_buf, gpts)])
        return gpts

    def grad_field(self, shape, pts: np.ndarray, gout: np.ndarray, cells: np.ndarray, n_points: int) -> np.ndarray:
        """(C, Z, Y, X): the gradient wrt the field of sum(gout * values), from the forward's cells
        of the first ``n_points`` points."""
        C, Z, Y, X = (int(n) for n in shape)
        n_cells = (X - 1) * (Y - 1) * (Z - 1)
        order = stable_order(cells[:n_points]).astype(np.int32)
        start = np.zeros(n_cells + 1, np.int32)
        np.cumsum(np.bincount(cells[:n_points], minlength=n_cells), out=start[1:])
        gfield = np.empty((C, Z, Y, X), gout.dtype)
        Pp = pts.shape[1]
        prog = self._program(gout.dtype)
        with self.call() as io:
            p_buf, go_buf = io.input(pts, "pts"), io.input(gout, "gout")
            o_buf, s_buf = io.input(order, "order"), io.input(start, "start")
            sums = io.scratch("sums", (n_cells * C * 8 + 2 * GUARD) * gout.itemsize)
            g_buf = io.output(gfield, "gfield")
            dims = np.int32(C), np.int32(X), np.int32(Y), np.int32(Z)
            self.launch(prog, "sample_cell_sums", (round_up(n_cells, CELLS_PER_ITEM) // CELLS_PER_ITEM,), None,
                        p_buf, go_buf, o_buf, s_buf, sums, np.int32(n_cells), np.int32(Pp), *dims)
            self.launch(prog, "sample_grad_field", (round_up(X, 8) // 8, Y, Z), None, sums, g_buf,
                        np.int32(n_cells), *dims)
            io.fetch([(g_buf, gfield)])
        return gfield


def default_sampler() -> FieldSampler:
    """The process-wide sampler (its programs and buffers serve every call)."""
    return runtime.shared(FieldSampler)


def _padded(x: np.ndarray, Pp: int) -> np.ndarray:
    out = np.zeros((x.shape[0], Pp), x.dtype)
    out[:, :x.shape[1]] = x
    return out


class _Sample(torch.autograd.Function):
    @staticmethod
    def forward(ctx, field, points, sampler):
        f = np.ascontiguousarray(field.detach().numpy())
        P = points.shape[1]
        pts = _padded(points.detach().numpy(), round_up(max(P, 1), 8))
        out, cells = sampler.forward(f, pts)
        ctx.sampler, ctx.field_np, ctx.pts, ctx.cells, ctx.n = sampler, f, pts, cells, P
        return torch.from_numpy(out[:, :P])

    @staticmethod
    def backward(ctx, grad):
        gout = _padded(np.ascontiguousarray(grad.detach().numpy(), dtype=ctx.field_np.dtype), ctx.pts.shape[1])
        gfield = gpoints = None
        if ctx.needs_input_grad[0]:
            gfield = torch.from_numpy(ctx.sampler.grad_field(ctx.field_np.shape, ctx.pts, gout, ctx.cells, ctx.n))
        if ctx.needs_input_grad[1]:
            gpoints = torch.from_numpy(ctx.sampler.grad_points(ctx.field_np, ctx.pts, gout)[:, :ctx.n])
        return gfield, gpoints, None


def sample(field: torch.Tensor, points: torch.Tensor, sampler: FieldSampler | None = None) -> torch.Tensor:
    """(C, P) trilinear samples of ``field`` (C, Z, Y, X) at ``points`` (3, P) in voxel units (rows
    x, y, z); clamped to the border outside. Differentiable in both (see the module doc)."""
    if field.dim() != 4 or not 1 <= field.shape[0] <= MAX_CHANNELS:
        raise InputError(f"field must be (C, Z, Y, X) with 1 <= C <= {MAX_CHANNELS}, got {tuple(field.shape)}")
    if min(field.shape[1:]) < 2:
        raise InputError(f"a field grid needs at least 2 voxels per axis, got {tuple(field.shape[1:])}")
    if points.dim() != 2 or points.shape[0] != 3:
        raise InputError(f"points must be (3, P), got {tuple(points.shape)}")
    if field.dtype not in (torch.float32, torch.float64) or points.dtype != field.dtype:
        raise InputError(f"field and points must share a float32 or float64 dtype, got {field.dtype}, {points.dtype}")
    if field.device.type != "cpu" or points.device.type != "cpu":
        raise InputError("field and points must be CPU tensors (the kernels read host memory)")
    if points.shape[1] == 0:
        return field.new_zeros((field.shape[0], 0)) + 0 * field.sum()
    return _Sample.apply(field, points, sampler or default_sampler())
