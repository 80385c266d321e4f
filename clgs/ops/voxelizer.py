"""Gaussian voxelizer (OpenCL): the density field of a Gaussian model on a grid or at points.

The field is ``mu(x) = sum_i rho_i exp(-d^T P_i d / 2)`` with ``d = x - p_i`` and ``P_i`` the
precision (inverse covariance). Each Gaussian is cut to its 3-sigma axis-aligned box
(``clgs.reference.gaussians.axis_extent``): it contributes at ``x`` only where ``-e_i <= x - p_i <= e_i``
on every axis. ``clgs.reference.voxelization`` computes the same field, with the same cut, in
plain torch.

Public API (torch autograd ops, differentiable wrt means, scales, quats and densities; float32
or float64 by the inputs' dtype; CPU tensors):

* ``voxelize(means, scales, quats, densities, grid) -> (Z, Y, X)``: the field at the sample
  points of a ``clgs.geometry.Grid``; an axis-aligned sub-block (``grid.block(start, size)``,
  e.g. a random 32^3 patch for a TV or density loss) gives bitwise the same values as the same
  region of the full grid, at the cost of the block only.
* ``voxelize_points(means, scales, quats, densities, points) -> (M,)``: the field at arbitrary
  points (M, 3), e.g. the overlap count at the reference centres of the shape-guided start.
* ``voxelize_precision(means, prec, densities, extent, grid_or_points)``: the same from a packed
  precision (N, 6) and 3-sigma half-widths (N, 3) (``gaussians.precision``/``axis_extent``),
  differentiable wrt means, prec and densities: lets a training step build them once for all
  Gaussians and reuse them for several blocks (for a 32^3 block of a 50k-Gaussian scene that torch
  work costs more than the kernel).
* ``cov_prec(scales, quats, cov=True, prec=True, extent=False)``: covariance, precision (N, 6)
  and 3-sigma half-widths (N, 3) in one OpenCL pass, differentiable (closed-form backward kernel);
  the values of ``gaussians.covariance`` / ``precision`` / ``axis_extent``. ``voxelize`` and
  ``voxelize_points`` build their precisions with it; the trainer builds the projector's
  covariances with it too.
* ``Voxelizer``: owns the compiled programs and scratch buffers; the module functions share one.

The TV loss on a small block (R2-Gaussian's random 32^3 patch) has a fused operator,
:class:`clgs.ops.tv_patch.PatchTV` (culling, field, TV and gradient rows on the device in one batch,
one wait): ``cl/tv_patch.cl`` builds on this file (its ``vox_grid`` writing a padded layout, the
gradient sums shared with ``vox_grid_grad``) with kernels of its own (``patch_*``).

Accuracy: float32 kernels match the float32 torch reference to ~1e-7 of the peak. For very thin
Gaussians (scale ratios near 1e-3) ``d^T P d`` cancels in float32 whatever the order of
operations (P holds 1/s^2 next to O(1) values), so the field near them is good to about 1% of
their peak in float32 (and to ~1e-10 in float64).

How the kernels (``cl/voxelizer.cl``) bin, lay out and sum, and their compiled variants:
docs/kernels.md.
"""
from __future__ import annotations

import math
import re

import numpy as np
import torch

from clgs import runtime
from clgs.errors import InputError
from clgs.geometry import Grid
from clgs.ops.sorting import stable_order
from clgs.runtime import Operator, round_up

SOURCE = "voxelizer.cl"


def _kernel_constant(name: str) -> int:
    """An integer ``#define`` of the kernel file, so that a record size is written in one place."""
    match = re.search(rf"^#define {name} (\d+)\s*$", (runtime.cl_source_dir() / SOURCE).read_text(), re.M)
    if match is None:
        raise RuntimeError(f"{SOURCE} defines no {name}")
    return int(match.group(1))


GSTRIDE = _kernel_constant("GSTRIDE")  # reals per packed Gaussian: p (3), rho, P (6), e (3), pad (3)
GRADSTRIDE = _kernel_constant("GRADSTRIDE")  # reals per gradient row: dp (3), dP (6), drho
_LOCAL = 8  # one work-group size for every kernel: PoCL recompiles per (kernel, local size)
_MIN_CHUNK = 256  # Gaussians per binning work-item, at least
_MAX_HIST = 1 << 22  # cap on (cells x chunks) histogram entries
# small grids (a TV patch): bin by one work-item in one launch below these many bricks and
# bricks x Gaussians (the list's room); in the backward, no sort below this many bytes of dL/dfield.
# 2^19 pairs (8k Gaussians on 64 bricks): past about 4-8k Gaussians on a 32^3 grid the parallel
# counting sort, round trip included, is faster (``clgs bench train --method shape --alternate``);
# the same bits either way
SMALL_CELLS = 512
_SMALL_PAIRS = 1 << 19
_UNSORTED_BYTES = 1 << 20



def np_dtype(dtype: torch.dtype):
    if dtype == torch.float32:
        return np.float32
    if dtype == torch.float64:
        return np.float64
    raise TypeError(f"voxelizer inputs must be float32 or float64 tensors, got {dtype}")


def _tiny(dt) -> float:
    """The quaternion norm below which it is clamped, as ``gaussians.quaternion_to_rotation``."""
    return float(np.finfo(dt).tiny) ** 0.5


def grid_axes(grid: Grid, dtype=np.float64):
    """Sample coordinates along x, y, z of ``grid`` (computed in float64 as ``Grid.points`` does,
    then rounded to ``dtype``), so blocks and full grids see the very same numbers."""
    return [
        (np.float64(grid.origin[a]) + np.float64(grid.spacing[a]) * np.arange(grid.shape[2 - a])).astype(dtype)
        for a in range(3)
    ]


def pack_gaussians(means, prec, densities, extent) -> torch.Tensor:
    """(N, 16) rows ``[p (3), rho, P (6), e (3), 0, 0, 0]`` as the kernels read them."""
    n = means.shape[0]
    pad = means.new_zeros((n, GSTRIDE - 13))
    return torch.cat([means, densities.reshape(n, 1), prec, extent, pad], 1).contiguous()


def columns(x: torch.Tensor) -> torch.Tensor:
    """(N, K) -> contiguous (K, N) copy, written through a transposed view (several times faster
    on a CPU than ``x.t().contiguous()`` for a few columns)."""
    out = x.new_empty((x.shape[1], x.shape[0]))
    out.t().copy_(x)
    return out


def grid_candidates(means: torch.Tensor, half_widths: torch.Tensor, grid: Grid):
    """Indices (ascending) of the Gaussians whose box ``mean +- half_widths`` ((N, 3), or (N,) for
    a cube) can meet ``grid``'s samples, or None when that is all of them.

    The field on the grid and every gradient are the same with only these Gaussians: the others
    contribute exactly 0, and the order is kept, so every sum runs in the same order. A voxel of
    margin covers rounding. For a 32^3 block of a 50k-Gaussian scene this leaves a few percent of
    the Gaussians, so packing, binning (and, with a cheap bound such as ``3 max(scales)``, the
    precisions of the caller) cost a few percent too."""
    with torch.no_grad():
        n = means.shape[0]
        if n == 0:
            return None
        h = np.asarray(grid.spacing, np.float64)
        size = np.asarray(grid.shape[::-1], np.float64)  # (x, y, z)
        centre = torch.as_tensor(np.asarray(grid.origin, np.float64) + 0.5 * (size - 1) * h, dtype=means.dtype)
        reach = torch.as_tensor(0.5 * (size + 1) * h, dtype=means.dtype)  # half the samples' span + a voxel
        e = half_widths.detach()
        e = e if e.dim() == 2 else e.reshape(n, 1)
        # |p - c| - e <= reach on every axis (in the row layout: cheaper than transposing to columns)
        inside = ((means.detach() - centre).abs_().sub_(e) <= reach).all(1)
        idx = inside.nonzero().squeeze(1)
        return None if idx.numel() == n else idx


def brick_cells(grid: Grid, brick_y: int = 8, brick_z: int = 8) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """Bricks (8 x ``brick_y`` x ``brick_z`` samples) of ``grid`` as binning cells: (lower corner,
    1 / brick size, bricks per axis), all (x, y, z)."""
    nz, ny, nx = (int(s) for s in grid.shape)
    h = np.asarray(grid.spacing, np.float64)
    brick = np.array([8, brick_y, brick_z], np.float64) * h
    origin = np.asarray(grid.origin, np.float64) - 0.5 * h
    return origin, 1.0 / brick, (-(-nx // 8), -(-ny // brick_y), -(-nz // brick_z))


def check_grid(grid: Grid):
    """A clear error for anything but a 3-D :class:`~clgs.geometry.Grid` with positive, finite spacing."""
    if not isinstance(grid, Grid):
        raise TypeError(f"grid must be a clgs.geometry.Grid, got {type(grid).__name__}")
    if len(grid.shape) != 3 or min(grid.shape) < 1:
        raise InputError(f"grid shape must be 3 positive sizes (Z, Y, X), got {grid.shape}")
    if min(grid.spacing) <= 0 or not np.all(np.isfinite(grid.spacing)) or not np.all(np.isfinite(grid.origin)):
        raise InputError(f"grid spacing must be positive and finite, origin finite: {grid}")


class _PointBins:
    """Points sorted by a coarse cell grid, each cell padded to a multiple of 8.

    ``slot[m]`` is where input point ``m`` sits in the padded, sorted arrays ``X, Y, Z``.
    """

    def __init__(self, points: np.ndarray, half_width: float):
        m = points.shape[0]
        dt = points.dtype.type
        # the cell grid as the kernels see it: origin and inverse size rounded to the points' dtype
        lo = points.min(0).astype(np.float64)  # exact in the points' dtype
        extent = points.max(0).astype(np.float64) - lo
        # cells about one Gaussian box wide (but not below the coordinates' resolution), grown
        # until occupied cells hold ~8 points (full lanes) and there are at most 2^21 cells
        size = max(2.0 * half_width, float(extent.max()) / 128.0, 1e-4 * float(np.abs(points).max()), 1e-12)
        for _ in range(60):
            inv = float(dt(1.0 / size))
            nc = np.floor(extent * inv).astype(np.int64) + 1
            if nc.prod() <= (1 << 21):
                cell = self._cells(points, lo, inv, nc)
                occupied = np.count_nonzero(np.bincount(cell, minlength=int(nc.prod())))
                if m / occupied >= 8 or occupied == 1:
                    break
            size *= 1.5
        ncells = int(nc.prod())
        order = stable_order(cell)
        counts = np.bincount(cell, minlength=ncells)
        padded = (counts + 7) // 8 * 8
        pstart = np.zeros(ncells + 1, np.int64)
        np.cumsum(padded, out=pstart[1:])
        first = np.zeros(ncells + 1, np.int64)
        np.cumsum(counts, out=first[1:])
        sorted_cell = cell[order]
        rank = np.arange(m) - first[sorted_cell]
        slot = np.empty(m, np.int64)
        slot[order] = pstart[sorted_cell] + rank
        total = int(pstart[-1])
        coords = np.empty((3, total), points.dtype)
        coords[:, slot] = points.T
        # pads repeat their cell's first point (finite, and their incoming gradient is zero)
        cell_of_slot = np.repeat(np.arange(ncells), padded)
        is_pad = np.ones(total, bool)
        is_pad[slot] = False
        coords[:, is_pad] = coords[:, pstart[cell_of_slot[is_pad]]]
        self.slot = slot
        self.total = total
        self.X, self.Y, self.Z = (np.ascontiguousarray(c) for c in coords)
        self.chunk_cell = np.repeat(np.arange(ncells, dtype=np.int32), padded // 8)
        self.cell_pstart = pstart.astype(np.int32)
        self.origin = lo
        self.inv = inv
        self.nc = nc
        self.ncells = ncells

    @staticmethod
    def _cells(points, lo, inv, nc):
        idx = np.floor((points.astype(np.float64) - lo) * inv).astype(np.int64)
        idx = np.clip(idx, 0, nc - 1)
        return (idx[:, 2] * nc[1] + idx[:, 1]) * nc[0] + idx[:, 0]


class BrickOperator(Operator):
    """An operator over the voxel bricks (the voxelizer, the TV patch): ``brick`` rows (y, z) and
    one program per (precision, set of ``WANT_*`` gradients)."""

    def __init__(self, ctx=None, queue=None, brick=(8, 8)):
        super().__init__(ctx, queue)
        self.brick_y, self.brick_z = int(brick[0]), int(brick[1])

    def program(self, np_dtype, grads=()):
        """The variant for this precision and set of ``WANT_*`` gradients."""
        real = "double" if np_dtype == np.float64 else "float"

        def defines():
            d = {"REAL": real, "BRICK_Y": self.brick_y, "BRICK_Z": self.brick_z}
            d.update({g: True for g in grads})
            return d

        return self.variant((real, tuple(grads)), defines)


class Voxelizer(BrickOperator):
    """Runs ``cl/voxelizer.cl`` (an :class:`~clgs.runtime.Operator`): programs per (precision,
    gradient set), pooled scratch buffers, one call at a time. ``brick``: brick rows (y, z)."""

    SOURCE = SOURCE

    # ------------------------------------------------------------------------- plumbing

    def device_input(self, arr: np.ndarray):
        """(buffer, array): a read-only buffer of ``arr`` and the array it reads, which the caller
        keeps until the kernels are done (empty arrays become one element: no zero-size buffers)."""
        arr = np.ascontiguousarray(arr)
        if arr.size == 0:
            arr = np.zeros(1, arr.dtype)
        return self.io.wrap(arr), arr

    def run(self, prog, name: str, n_items: int, *args):
        """Launch kernel ``name`` over ``n_items`` work-items in groups of ``_LOCAL``."""
        return self.launch(prog, name, (round_up(max(n_items, 1), _LOCAL),), (_LOCAL,), *args)

    def _bin(self, prog, gbuf, n, real, origin, inv, nc, home=False, copy=False):
        """Counting sort of Gaussians into cells: (start (ncells+1), list, list length), where
        ``list`` holds Gaussian indices, or with ``copy`` their packed records in list order.

        ``home``: each kept Gaussian goes to one cell only (its clamped centre's), so the list is
        the kept Gaussians sorted by place."""
        ncells = int(np.prod(nc))
        nchunks = max(1, min(math.ceil(n / _MIN_CHUNK), _MAX_HIST // max(ncells, 1), 256))
        chunk = math.ceil(n / nchunks)
        cell_args = [real(origin[0]), real(origin[1]), real(origin[2]), real(inv[0]), real(inv[1]), real(inv[2]),
                     np.int32(nc[0]), np.int32(nc[1]), np.int32(nc[2])]
        hist = self.io.scratch("hist", 4 * ncells * nchunks)
        total = self.io.scratch("total", 4 * ncells)
        start = self.io.scratch("start", 4 * (ncells + 1))
        self.io.fill(hist, np.int32(0), 4 * ncells * nchunks)
        ranges = self.io.scratch("ranges", 32 * n)
        self.run(prog, "bin_count", nchunks, gbuf, np.int32(n), np.int32(chunk), np.int32(nchunks),
                  np.int32(bool(home)), *cell_args, hist, ranges)
        self.run(prog, "bin_cell_offsets", ncells, hist, np.int32(nchunks), np.int32(ncells), total)
        self.run(prog, "bin_scan", 1, total, np.int32(ncells), start)
        length_buf = np.empty(1, np.int32)
        self.io.copy(length_buf, start, src_offset=4 * ncells)
        length = int(length_buf[0])
        itemsize = GSTRIDE * np.dtype(real).itemsize if copy else 4
        if length < 0 or length * itemsize > self.ctx.devices[0].max_mem_alloc_size:
            raise MemoryError(
                f"{n} Gaussians meet too many of the {ncells} cells ({'over 2^31' if length < 0 else length} "
                "Gaussian-cell pairs): the Gaussians are very large for this grid; voxelize a coarser grid "
                "or smaller blocks, or bound the scales"
            )
        lst = self.io.scratch("list", 4 * max(length, 1))
        packed = self.io.scratch("packed", GSTRIDE * np.dtype(real).itemsize * max(length, 1)) if copy else lst
        if length > 0:
            self.run(prog, "bin_fill", nchunks, gbuf, np.int32(n), np.int32(chunk), np.int32(nchunks),
                      np.int32(nc[0]), np.int32(nc[1]), hist, ranges, start, lst, np.int32(bool(copy)), packed)
        return start, (packed if copy else lst), length

    # ------------------------------------------------------------------------- grid
    def brick_cells(self, grid: Grid) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
        """Bricks as binning cells: (lower corner, 1 / brick size, bricks per axis), all (x, y, z)."""
        return brick_cells(grid, self.brick_y, self.brick_z)

    def grid_forward(self, gauss: torch.Tensor, grid: Grid) -> torch.Tensor:
        """Field on ``grid`` from packed Gaussians ``gauss`` (N, 16) -> (Z, Y, X) tensor."""
        with self.call():
            check_grid(grid)
            dt = np_dtype(gauss.dtype)
            nz, ny, nx = (int(s) for s in grid.shape)
            out = np.zeros((nz, ny, nx), dt)
            n = gauss.shape[0]
            if n == 0:
                return torch.from_numpy(out)
            real = dt
            prog = self.program(dt)
            xs, ys, zs = grid_axes(grid, dt)
            nxp = round_up(nx, 8) + 8
            xs_p = np.concatenate([xs, (np.float64(grid.origin[0]) + np.float64(grid.spacing[0])
                                        * np.arange(nx, nxp)).astype(dt)])
            gnp = gauss.detach().numpy()
            gbuf, gkeep = self.device_input(gnp)
            xb, xk = self.device_input(xs_p)
            yb, yk = self.device_input(ys)
            zb, zk = self.device_input(zs)
            origin, inv, (nbx, nby, nbz) = self.brick_cells(grid)
            nbricks = nbx * nby * nbz
            if nbricks <= SMALL_CELLS and nbricks * n <= _SMALL_PAIRS:
                # a small grid (a TV patch): lists by one work-item, no host round trip
                start = self.io.scratch("start", 4 * (nbricks + 1))
                lst = self.io.scratch("list", 4 * nbricks * n)
                self.run(prog, "bin_small", 1, gbuf, np.int32(n), real(origin[0]), real(origin[1]),
                          real(origin[2]), real(inv[0]), real(inv[1]), real(inv[2]), np.int32(nbx), np.int32(nby),
                          np.int32(nbz), start, lst)
                packed, length, indexed = gbuf, 1, 1
            else:
                start, packed, length = self._bin(prog, gbuf, n, real, origin, inv, (nbx, nby, nbz), copy=True)
                lst, indexed = start, 0
            if length:
                obuf = self.io.output(out)
                self.run(prog, "vox_grid", nbricks, packed, start, lst, np.int32(indexed), xb, yb, zb,
                         np.int32(nx), np.int32(ny), np.int32(nz), np.int32(nbx), np.int32(nby), np.int32(nbricks),
                         obuf, np.int32(nx), np.int32(0))
                self.io.fetch([(obuf, out)])
            else:
                self.io.fetch([])  # nothing to read back: wait for the queue
            del gkeep, xk, yk, zk
            return torch.from_numpy(out)

    def grid_backward(self, gauss: torch.Tensor, grid: Grid, grad_out: torch.Tensor, want) -> torch.Tensor:
        """(N, 10) gradient rows ``[dp (3), dP (6), drho]`` from dL/dfield ``grad_out`` (Z, Y, X).

        ``want`` is a subset of ``("WANT_MEAN", "WANT_PREC", "WANT_RHO")``."""
        with self.call():
            dt = np_dtype(gauss.dtype)
            n = gauss.shape[0]
            grad = np.zeros((n, GRADSTRIDE), dt)
            if n == 0 or not want:
                return torch.from_numpy(grad)
            nz, ny, nx = (int(s) for s in grid.shape)
            prog = self.program(dt, tuple(sorted(want)))
            xs, ys, zs = grid_axes(grid, dt)
            nxp = round_up(nx, 8) + 8
            xs_p = np.concatenate([xs, (np.float64(grid.origin[0]) + np.float64(grid.spacing[0])
                                        * np.arange(nx, nxp)).astype(dt)])
            g_np = grad_out.detach().to(gauss.dtype).contiguous().numpy()
            gbuf, gkeep = self.device_input(gauss.detach().numpy())
            xb, xk = self.device_input(xs_p)
            yb, yk = self.device_input(ys)
            zb, zk = self.device_input(zs)
            ob, ok = self.device_input(g_np)
            if g_np.nbytes <= _UNSORTED_BYTES:  # dL/dfield stays in cache: no sort, no round trip
                order, kept, sort = gbuf, n, 0
            else:
                _, order, kept = self._bin(prog, gbuf, n, dt, *self.brick_cells(grid), home=True)
                sort = 1
            if kept:
                rbuf = self.io.output(grad, initial=True)
                self.run(prog, "vox_grid_grad", kept, gbuf, order, np.int32(sort), np.int32(kept), xb, yb, zb,
                          np.int32(nx), np.int32(ny), np.int32(nz), ob, rbuf)
                self.io.fetch([(rbuf, grad)])
            else:
                self.io.fetch([])  # nothing to read back: wait for the queue
            del gkeep, xk, yk, zk, ok
            return torch.from_numpy(grad)

    # ------------------------------------------------------------------------- matrices
    def cov_prec_forward(self, scales: torch.Tensor, quats: torch.Tensor, want: int):
        """(covariance, precision, 3-sigma half-widths) of N Gaussians, (N, 6), (N, 6), (N, 3), each
        computed when bit 0, 1, 2 of ``want`` is set (else an empty tensor); no autograd."""
        with self.call():
            dt = np_dtype(scales.dtype)
            n = scales.shape[0]
            shapes = ((n, 6), (n, 6), (n, 3))
            outs = [np.empty(shape if want >> b & 1 else (0,), dt) for b, shape in enumerate(shapes)]
            if n:
                prog = self.program(dt)
                sb, sk = self.device_input(scales.detach().numpy())
                qb, qk = self.device_input(quats.detach().numpy())
                bufs = [self.io.output(o) if o.size else sb for o in outs]
                self.run(prog, "cov_prec", -(-n // 8), sb, qb, np.int32(n), np.int32(want), dt(_tiny(dt)), *bufs)
                self.io.fetch([(b, o) for b, o in zip(bufs, outs) if o.size])
                del sk, qk
            return tuple(torch.from_numpy(o) for o in outs)

    def cov_prec_backward(self, scales: torch.Tensor, quats: torch.Tensor, g_cov, g_prec):
        """(dL/dscales (N, 3), dL/dquats (N, 4)) from the packed gradients of the covariance and of
        the precision (N, 6) (either may be None)."""
        with self.call():
            dt = np_dtype(scales.dtype)
            n = scales.shape[0]
            ds, dq = np.empty((n, 3), dt), np.empty((n, 4), dt)
            if n:
                prog = self.program(dt)
                sb, sk = self.device_input(scales.detach().numpy())
                qb, qk = self.device_input(quats.detach().numpy())
                has, keep, gbufs = 0, [], []
                for bit, g in enumerate((g_cov, g_prec)):
                    if g is None:
                        gbufs.append(sb)
                        continue
                    has |= 1 << bit
                    gb, gk = self.device_input(g.detach().to(scales.dtype).contiguous().numpy())
                    gbufs.append(gb)
                    keep.append(gk)
                dsb, dqb = self.io.output(ds), self.io.output(dq)
                self.run(prog, "cov_prec_grad", -(-n // 8), sb, qb, np.int32(n), np.int32(has), dt(_tiny(dt)),
                         *gbufs, dsb, dqb)
                self.io.fetch([(dsb, ds), (dqb, dq)])
                del sk, qk, keep
            return torch.from_numpy(ds), torch.from_numpy(dq)

    # ------------------------------------------------------------------------- points
    def point_bins(self, points: np.ndarray, extent: torch.Tensor) -> _PointBins:
        half = float(torch.median(extent).item()) if extent.numel() else 1.0
        return _PointBins(points, half)

    def points_forward(self, gauss: torch.Tensor, points: np.ndarray, bins: _PointBins | None = None):
        """Field at ``points`` (M, 3) -> ((M,) tensor, the point bins for the backward)."""
        with self.call():
            dt = np_dtype(gauss.dtype)
            m, n = points.shape[0], gauss.shape[0]
            if m == 0:
                return torch.zeros(0, dtype=gauss.dtype), None
            if bins is None:
                bins = self.point_bins(points, gauss[:, 10:13])
            if n == 0:
                return torch.zeros(m, dtype=gauss.dtype), bins
            prog = self.program(dt)
            gbuf, gkeep = self.device_input(gauss.detach().numpy())
            start, packed, length = self._bin(prog, gbuf, n, dt, bins.origin, (bins.inv,) * 3, bins.nc, copy=True)
            out = np.zeros(bins.total, dt)
            if length:
                xb, xk = self.device_input(bins.X)
                yb, yk = self.device_input(bins.Y)
                zb, zk = self.device_input(bins.Z)
                cb, ck = self.device_input(bins.chunk_cell)
                obuf = self.io.output(out)
                nchunks = bins.total // 8
                self.run(prog, "vox_points", nchunks, packed, start, xb, yb, zb, cb, np.int32(nchunks), obuf)
                self.io.fetch([(obuf, out)])
                del xk, yk, zk, ck
            else:
                self.io.fetch([])  # nothing to read back: wait for the queue
            del gkeep
            return torch.from_numpy(out[bins.slot]), bins

    def points_backward(self, gauss: torch.Tensor, bins: _PointBins, grad_out: torch.Tensor, want) -> torch.Tensor:
        """(N, 10) gradient rows from dL/dfield at the points (M,)."""
        with self.call():
            dt = np_dtype(gauss.dtype)
            n = gauss.shape[0]
            grad = np.zeros((n, GRADSTRIDE), dt)
            if n == 0 or bins is None or not want:
                return torch.from_numpy(grad)
            prog = self.program(dt, tuple(sorted(want)))
            gp = np.zeros(bins.total, dt)
            gp[bins.slot] = grad_out.detach().to(gauss.dtype).numpy()
            gbuf, gkeep = self.device_input(gauss.detach().numpy())
            xb, xk = self.device_input(bins.X)
            yb, yk = self.device_input(bins.Y)
            zb, zk = self.device_input(bins.Z)
            pb, pk = self.device_input(gp)
            sb, sk = self.device_input(bins.cell_pstart)
            rbuf = self.io.output(grad)
            o, nc = bins.origin, bins.nc
            self.run(prog, "vox_points_grad", n, gbuf, np.int32(n),
                      dt(o[0]), dt(o[1]), dt(o[2]), dt(bins.inv), dt(bins.inv), dt(bins.inv),
                      np.int32(nc[0]), np.int32(nc[1]), np.int32(nc[2]), sb, xb, yb, zb, pb, rbuf)
            self.io.fetch([(rbuf, grad)])
            del gkeep, xk, yk, zk, pk, sk
            return torch.from_numpy(grad)


# ----------------------------------------------------------------------------- autograd ops
def default_voxelizer() -> Voxelizer:
    """The process-wide voxelizer (programs and scratch buffers shared by every call)."""
    return runtime.shared(Voxelizer)


def wanted_gradients(needs) -> tuple:
    names = ("WANT_MEAN", "WANT_PREC", "WANT_RHO")
    return tuple(name for name, need in zip(names, needs) if need)


def _split(grad: torch.Tensor, needs):
    return (grad[:, 0:3] if needs[0] else None, grad[:, 3:9] if needs[1] else None,
            grad[:, 9] if needs[2] else None)


class _GridField(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, prec, densities, extent, grid, vox):
        gauss = pack_gaussians(means, prec, densities, extent)
        ctx.save_for_backward(gauss)
        ctx.grid, ctx.vox = grid, vox
        return vox.grid_forward(gauss, grid)

    @staticmethod
    def backward(ctx, grad_out):
        (gauss,) = ctx.saved_tensors
        needs = ctx.needs_input_grad[:3]
        grad = ctx.vox.grid_backward(gauss, ctx.grid, grad_out, wanted_gradients(needs))
        return (*_split(grad, needs), None, None, None)


class _PointField(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, prec, densities, extent, points, vox):
        gauss = pack_gaussians(means, prec, densities, extent)
        out, bins = vox.points_forward(gauss, points)
        ctx.save_for_backward(gauss)
        ctx.bins, ctx.vox = bins, vox
        return out

    @staticmethod
    def backward(ctx, grad_out):
        (gauss,) = ctx.saved_tensors
        needs = ctx.needs_input_grad[:3]
        grad = ctx.vox.points_backward(gauss, ctx.bins, grad_out, wanted_gradients(needs))
        return (*_split(grad, needs), None, None, None)


class _CovPrec(torch.autograd.Function):
    """The kernels' matrices with their closed-form backward in one kernel (see ``cov_prec``)."""

    @staticmethod
    def forward(ctx, scales, quats, want, vox):
        ctx.set_materialize_grads(False)
        cov, prec, extent = vox.cov_prec_forward(scales, quats, want)
        ctx.save_for_backward(scales, quats)
        ctx.vox = vox
        ctx.mark_non_differentiable(extent)
        return cov, prec, extent

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_cov, g_prec, _g_extent):
        scales, quats = ctx.saved_tensors
        if not any(ctx.needs_input_grad[:2]) or (g_cov is None and g_prec is None):
            return None, None, None, None
        ds, dq = ctx.vox.cov_prec_backward(scales, quats, g_cov, g_prec)
        return (ds if ctx.needs_input_grad[0] else None), (dq if ctx.needs_input_grad[1] else None), None, None


def cov_prec(scales, quats, cov: bool = True, prec: bool = True, extent: bool = False,
             voxelizer: Voxelizer | None = None):
    """(covariance, precision, half-widths) of N Gaussians from activated scales (N, 3) and raw
    quaternions (N, 4), as ``gaussians.covariance`` (N, 6), ``gaussians.precision`` (N, 6)
    and ``gaussians.axis_extent`` (N, 3, no gradient), each None when not asked.

    One OpenCL kernel for all three and one for the closed-form backward: on a CPU this is ~20x
    cheaper than the same maths as element-wise torch on (N,) columns (dozens of passes over
    50k-long buffers each way), and asking for several outputs costs one pass."""
    if scales.dim() != 2 or scales.shape[1] != 3 or quats.shape != (scales.shape[0], 4):
        raise InputError(f"expected scales (N, 3) and quats (N, 4), got {tuple(scales.shape)}, {tuple(quats.shape)}")
    if quats.dtype != scales.dtype:
        raise TypeError("scales and quats must share one dtype (float32 or float64)")
    want = int(bool(cov)) | int(bool(prec)) << 1 | int(bool(extent)) << 2
    if not want:
        return None, None, None
    vox = voxelizer or default_voxelizer()
    if torch.is_grad_enabled() and (scales.requires_grad or quats.requires_grad):
        out = _CovPrec.apply(scales.contiguous(), quats.contiguous(), want, vox)
    else:
        out = vox.cov_prec_forward(scales.detach().contiguous(), quats.detach().contiguous(), want)
    return tuple(o if want >> b & 1 else None for b, o in enumerate(out))


def _prepare(means, scales, quats, densities):
    """Checks shapes, dtype and finiteness; returns (precision, extent) for the kernels."""
    for name, t in (("means", means), ("scales", scales), ("quats", quats), ("densities", densities)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch tensor, got {type(t).__name__}")
        if t.device.type != "cpu":
            raise InputError(f"{name} is on {t.device}; the OpenCL voxelizer takes CPU tensors (use .cpu())")
    n = means.shape[0] if means.dim() == 2 else -1
    if means.shape != (n, 3) or scales.shape != (n, 3) or quats.shape != (n, 4) or densities.shape != (n,):
        raise InputError(
            "expected means (N, 3), scales (N, 3), quats (N, 4), densities (N,); got "
            f"{tuple(means.shape)}, {tuple(scales.shape)}, {tuple(quats.shape)}, {tuple(densities.shape)}"
        )
    dtype = means.dtype
    np_dtype(dtype)
    if any(t.dtype != dtype for t in (scales, quats, densities)):
        raise TypeError("means, scales, quats and densities must share one dtype (float32 or float64)")
    with torch.no_grad():
        if n and not (torch.isfinite(means).all() and torch.isfinite(densities).all() and torch.isfinite(quats).all()):
            raise InputError("means, quats and densities must be finite (found NaN or Inf)")
        if n and not (scales > 0).all():
            raise InputError("scales must be positive (activated standard deviations)")
    _, prec, extent = cov_prec(scales, quats, cov=False, prec=True, extent=True)
    if n and not torch.isfinite(prec.detach()).all():
        raise InputError(
            f"scales too small for {dtype}: the precision 1/scale^2 overflows (smallest scale "
            f"{scales.detach().min().item():.3g}); clamp scales or use float64"
        )
    return prec, extent


def voxelize(means, scales, quats, densities, grid: Grid, voxelizer: Voxelizer | None = None) -> torch.Tensor:
    """The field of N Gaussians at the samples of ``grid`` (a ``Grid`` or ``Grid.block``): (Z, Y, X).

    means (N, 3) scene coordinates, scales (N, 3) activated std devs, quats (N, 4) raw (w, x, y, z),
    densities (N,) activated. Differentiable wrt all four.
    """
    prec, extent = _prepare(means, scales, quats, densities)
    check_grid(grid)
    return voxelize_precision(means, prec, densities, extent, grid, voxelizer)


def voxelize_points(means, scales, quats, densities, points, voxelizer: Voxelizer | None = None) -> torch.Tensor:
    """The field of N Gaussians at ``points`` (M, 3) (tensor or array, scene coordinates): (M,)."""
    prec, extent = _prepare(means, scales, quats, densities)
    if not isinstance(points, (torch.Tensor, np.ndarray)) and not isinstance(points, (list, tuple)):
        raise TypeError(f"points must be an (M, 3) tensor or array, got {type(points).__name__}")
    return voxelize_precision(means, prec, densities, extent, points, voxelizer)


def voxelize_precision(means, prec, densities, extent, where, voxelizer: Voxelizer | None = None,
                       cull: bool = True) -> torch.Tensor:
    """The field from a packed precision ``prec`` (N, 6) and half-widths ``extent`` (N, 3), at the
    samples of a ``Grid`` (-> (Z, Y, X)) or at points (M, 3) (-> (M,)). Differentiable wrt means,
    prec and densities (``extent`` only bounds the support). ``cull=False``: the caller has
    already kept only ``grid_candidates`` (skips that pass; the result is the same either way)."""
    n = means.shape[0] if means.dim() == 2 else -1
    if means.shape != (n, 3) or prec.shape != (n, 6) or densities.shape != (n,) or extent.shape != (n, 3):
        raise InputError(
            "expected means (N, 3), prec (N, 6), densities (N,), extent (N, 3); got "
            f"{tuple(means.shape)}, {tuple(prec.shape)}, {tuple(densities.shape)}, {tuple(extent.shape)}"
        )
    if any(t.dtype != means.dtype for t in (prec, densities, extent)):
        raise TypeError("means, prec, densities and extent must share one dtype (float32 or float64)")
    np_dtype(means.dtype)
    vox = voxelizer or default_voxelizer()
    extent = extent.detach()
    if isinstance(where, Grid):
        check_grid(where)
        idx = grid_candidates(means, extent, where) if cull else None  # same field, less to pack and bin
        if idx is not None:
            means, prec, densities, extent = (t.index_select(0, idx) for t in (means, prec, densities, extent))
        return _GridField.apply(means, prec, densities, extent, where, vox)
    pts = where.detach().cpu().numpy() if isinstance(where, torch.Tensor) else np.asarray(where)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must be (M, 3), got shape {pts.shape}")
    pts = np.ascontiguousarray(pts, dtype=np_dtype(means.dtype))
    if not np.all(np.isfinite(pts)):
        raise InputError("points must be finite (found NaN or Inf)")
    return _PointField.apply(means, prec, densities, extent, pts, vox)
