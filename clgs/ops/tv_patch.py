"""The fused TV patch operator (``cl/tv_patch.cl``): the total variation of the Gaussian field
on a small block and its gradient rows, from all N Gaussians, on the device in one batch.

:class:`PatchTV` computes ``tv3d`` (:mod:`clgs.fit.losses`) of the voxelizer's field on a block
(``clgs.ops.voxelizer.voxelize_precision``): the mean absolute difference between neighbouring
samples, over the axes with more than one sample, differentiable wrt means (N, 3), the packed
precision (N, 6) and densities (N,) (the 3-sigma half-widths ``extent`` only bound the support),
float32 or float64 by the inputs' dtype. :class:`TVPatchFunction` is its autograd op; the
training loss term and the fallback for large grids are :mod:`clgs.fit.tv_patch`'s.

Why fused: on a small patch few Gaussians reach it and the time goes to the host; here
everything from the N rows to the kept Gaussians' gradient rows runs on the device in one batch
of launches with one wait (docs/kernels.md). The backward to the Gaussians is computed in the
forward for a unit upstream gradient; autograd only scales and scatters the kept rows.

Results: the field is bitwise the voxelizer's (same brick lists in Gaussian index order, same
kernel); the TV value and the gradients equal those of ``tv3d`` + the voxelizer's backward to
float rounding (sums of the TV run in another order, and the upstream gradient multiplies the
rows instead of the field's gradient). Same input, same bits, every run.
"""
from __future__ import annotations

import math
import threading
import weakref

import numpy as np
import torch

from clgs.geometry import Grid
from clgs.metrics import tv_count
from clgs.ops.voxelizer import (
    GRADSTRIDE,
    GSTRIDE,
    BrickOperator,
    Voxelizer,
    brick_cells,
    default_voxelizer,
    grid_axes,
    np_dtype,
)
from clgs.runtime import round_up

_CHUNK = 512  # Gaussians per culling work-item (at least; at most _MAX_CHUNKS chunks)
_MAX_CHUNKS = 64
_GRAD_ITEMS = 128  # work-items of patch_grad (each takes every 128th kept Gaussian)
_ALIGN = 4096  # host block sections (sub-buffer origins must be aligned)
_LOCAL = 8  # the voxelizer's work-group size


def _tv_weights(shape, dt):
    """(w_x, w_y, w_z): each difference's weight in the TV, 1 / (number of differences over the
    three axes, see :func:`clgs.metrics.tv_count`), 0 for an axis of one sample."""

    count = tv_count(shape)
    w = dt(1) / dt(count) if count else dt(0)
    return [w if n > 1 else dt(0) for n in shape[::-1]]


class PatchTV(BrickOperator):
    """Runs ``cl/tv_patch.cl`` (an :class:`~clgs.runtime.Operator`): programs per (precision,
    gradient set), pooled buffers, one call at a time. ``brick``: the voxelizer's brick rows (y, z)."""

    SOURCE = "tv_patch.cl"

    def __init__(self, ctx=None, queue=None, brick=(8, 8)):
        super().__init__(ctx, queue, brick)
        self._cap_list = 1 << 16

    @classmethod
    def like(cls, voxelizer: Voxelizer) -> PatchTV:
        """A TV patch that runs where ``voxelizer`` runs, as it does: same context, queue, bricks
        and memory mode (wrapped host memory or copies)."""
        op = cls(voxelizer.ctx, voxelizer.queue, (voxelizer.brick_y, voxelizer.brick_z))
        op.io.host_memory = voxelizer.io.host_memory
        return op

    def _run(self, prog, name: str, n_items: int, *args):
        self.launch(prog, name, (round_up(max(n_items, 1), _LOCAL),), (_LOCAL,), *args)

    def _outputs(self, sections):
        """One pooled host block for several outputs, so a single map (or copy) brings them all back.
        ``sections``: [(dtype, count)] -> ([arrays], [sub-buffers], block array, block buffer, bytes)."""
        offs, end = [], 0
        for dtype, count in sections:
            offs.append(end)
            end = round_up(end + np.dtype(dtype).itemsize * max(count, 1), _ALIGN)
        arr, buf = self.io.host_block("out", end, _ALIGN)
        views = [arr[o:o + np.dtype(d).itemsize * c].view(d) for o, (d, c) in zip(offs, sections)]
        subs = [buf.get_sub_region(o, np.dtype(d).itemsize * max(c, 1)) for o, (d, c) in zip(offs, sections)]
        return views, subs, arr, buf, end

    def forward(self, means, prec, densities, extent, grid: Grid, want=(), field: bool = False):
        """(TV value (python float in the inputs' precision), kept indices (K,) int64, gradient rows
        (K, 10) for a unit upstream gradient or None, the field (Z, Y, X) or None).

        ``want``: the gradients to compute (``WANT_MEAN``, ``WANT_PREC``, ``WANT_RHO``); empty: none.

        One function: the launches are enqueued back to back on buffers carved from one block and
        waited for once; splitting them would scatter that buffer layout.
        """
        dt = np_dtype(means.dtype)
        n = int(means.shape[0])
        nz, ny, nx = (int(s) for s in grid.shape)
        pitch = round_up(nx, 8) + 16
        if n == 0:
            empty = np.zeros((0,), np.int64)
            return (0.0, torch.from_numpy(empty), torch.zeros((0, GRADSTRIDE), dtype=means.dtype) if want else None,
                    torch.zeros(grid.shape, dtype=means.dtype) if field else None)
        with self.call() as io:
            prog = self.program(dt, tuple(sorted(want)))
            mb, pb, db, eb = (io.input(t.detach().contiguous().numpy()) for t in (means, prec, densities, extent))
            xs, ys, zs = grid_axes(grid, dt)
            nxp = round_up(nx, 8) + 8
            xs_p = np.concatenate([xs, (np.float64(grid.origin[0]) + np.float64(grid.spacing[0])
                                        * np.arange(nx, nxp)).astype(dt)])
            xb, yb, zb = (io.input(a) for a in (xs_p, ys, zs))
            origin, inv, (nbx, nby, nbz) = brick_cells(grid, self.brick_y, self.brick_z)
            ncells = nbx * nby * nbz
            nchunks = max(1, min(_MAX_CHUNKS, math.ceil(n / _CHUNK)))
            chunk = math.ceil(n / nchunks)
            nchunks = math.ceil(n / chunk)
            cell_args = [dt(origin[0]), dt(origin[1]), dt(origin[2]), dt(inv[0]), dt(inv[1]), dt(inv[2]),
                         np.int32(nbx), np.int32(nby), np.int32(nbz)]
            item = np.dtype(dt).itemsize
            # the quick 8-wide test before cell_range: the bricks' span widened by a hundredth of a brick
            # (cell_range widens cells by a thousandth) and by the coordinates' rounding
            bsize = 1.0 / np.asarray(inv, np.float64)
            hi = origin + bsize * np.array([nbx, nby, nbz])
            far = [dt(v) for v in hi]
            slack = dt(0.01 * bsize.min() + 16 * np.finfo(dt).eps * (np.abs(origin).max() + np.abs(hi).max()))
            hist = io.scratch("p_hist", 4 * ncells * nchunks)
            count = io.scratch("p_count", 4 * nchunks)
            koff = io.scratch("p_koff", 4 * nchunks)
            kept = io.scratch("p_kept", 4 * n)
            start = io.scratch("p_start", 4 * (ncells + 1))
            packed = io.scratch("p_packed", item * GSTRIDE * n)
            fsize = item * ((nz * ny + 1) * pitch + 16)
            fbuf = io.scratch("p_field", fsize)
            gbuf = io.scratch("p_gout", fsize)
            sections = [(np.int32, 4), (dt, 3 * nz), (np.int32, n)] + ([(dt, n * GRADSTRIDE)] if want else [])
            views, subs, block, block_b, nbytes = self._outputs(sections)
            meta, part, kidx = views[:3]
            meta_b, part_b, kidx_b = subs[:3]
            grad, grad_b = (views[3], subs[3]) if want else (None, None)
            w = _tv_weights((nz, ny, nx), dt)
            run = self._run
            for _attempt in range(3):
                cap = self._cap_list
                lst = io.scratch("p_list", 4 * cap)
                run(prog, "patch_cull", nchunks, mb, eb, np.int32(n), np.int32(chunk), np.int32(nchunks),
                    *cell_args, *far, slack, hist, count, kept)
                run(prog, "patch_scan", 1, count, hist, np.int32(nchunks), np.int32(ncells), np.int32(cap),
                    koff, start, meta_b)
                run(prog, "patch_fill", nchunks, mb, pb, db, eb, np.int32(chunk), np.int32(nchunks),
                    *cell_args, count, kept, koff, hist, meta_b, packed, kidx_b, lst)
                run(prog, "vox_grid", ncells, packed, start, lst, np.int32(1), xb, yb, zb, np.int32(nx),
                    np.int32(ny), np.int32(nz), np.int32(nbx), np.int32(nby), np.int32(ncells), fbuf,
                    np.int32(pitch), np.int32(8))
                run(prog, "patch_tv", nz, fbuf, np.int32(nx), np.int32(ny), np.int32(nz), np.int32(pitch),
                    w[0], w[1], w[2], gbuf, part_b)
                if want:
                    run(prog, "patch_grad", _GRAD_ITEMS, packed, meta_b, xb, yb, zb, np.int32(nx),
                        np.int32(ny), np.int32(nz), np.int32(pitch), gbuf, grad_b)
                io.fetch([(block_b, block[:nbytes])])  # the one wait
                if not meta[2]:
                    break
                pairs = int(meta[1])
                if pairs >= (1 << 31) - 1 or 4 * pairs > self.device.max_mem_alloc_size:
                    raise MemoryError(
                        f"TV patch: {n} Gaussians meet the patch's {ncells} bricks {pairs} times (too many to "
                        "list): the Gaussians are very large for this patch; bound the scales or use a smaller patch")
                self._cap_list = min(round_up(pairs + pairs // 4 + 1, 1 << 12), (1 << 31) - 1)
            else:  # pragma: no cover - the capacity is set from the count of the run before
                raise RuntimeError("TV patch: the brick lists kept overflowing")
            k = int(meta[0])
            # the TV as tv3d defines it: all absolute differences over their count; the slices'
            # partial sums are added in float64
            sums = part[:3 * nz].reshape(nz, 3).astype(np.float64).sum(0)
            count = tv_count((nz, ny, nx))
            total = sum(float(sums[a]) for a, size in ((2, nz), (1, ny), (0, nx)) if size > 1)
            value = dt(total / count) if count else dt(0)
            idx = torch.from_numpy(kidx[:k].astype(np.int64))
            rows = None if grad is None else torch.from_numpy(grad[:k * GRADSTRIDE].reshape(k, GRADSTRIDE).copy())
            out_field = None
            if field:
                fh, fh_b = io.host_block("field", fsize, _ALIGN)
                io.copy(fh_b, fbuf, byte_count=fsize)
                io.fetch([(fh_b, fh[:fsize])])
                rows_f = fh[:fsize].view(dt)[8:8 + nz * ny * pitch].reshape(nz, ny, pitch)[:, :, :nx]
                out_field = torch.from_numpy(np.ascontiguousarray(rows_f))
            return float(value), idx, rows, out_field


class TVPatchFunction(torch.autograd.Function):
    """The autograd op of :meth:`PatchTV.forward`: (means, prec, densities, extent, grid, op) -> TV."""

    @staticmethod
    def forward(ctx, means, prec, densities, extent, grid, runner):
        needs = ctx.needs_input_grad[:3]
        names = ("WANT_MEAN", "WANT_PREC", "WANT_RHO")
        value, idx, rows, _ = runner.forward(means, prec, densities, extent, grid,
                                             tuple(name for name, need in zip(names, needs) if need))
        ctx.n = means.shape[0]
        ctx.idx, ctx.rows = idx, rows
        return means.new_tensor(value)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        needs = ctx.needs_input_grad[:3]
        idx, rows, n = ctx.idx, ctx.rows, ctx.n
        scaled = rows * g
        out: list = []
        for need, (a, b) in zip(needs, ((0, 3), (3, 9), (9, 10))):
            if not need:
                out.append(None)
                continue
            full = rows.new_zeros((n, b - a))
            full.index_copy_(0, idx, scaled[:, a:b])
            out.append(full if b - a > 1 else full.reshape(n))
        return (*out, None, None, None)


_lock = threading.Lock()
_matching: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # Voxelizer -> its PatchTV


def patch_operator(voxelizer: Voxelizer | None = None) -> PatchTV:
    """The :class:`PatchTV` that runs like ``voxelizer`` (one each, kept with it, so its pooled
    buffers live as long); None: that of the process-wide voxelizer on the current device."""
    voxelizer = voxelizer or default_voxelizer()
    with _lock:
        op = _matching.get(voxelizer)
        if op is None:
            op = _matching[voxelizer] = PatchTV.like(voxelizer)
        return op
