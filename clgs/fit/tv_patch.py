"""Total variation of the Gaussian field on a small block (the TV patch of R2-Gaussian's loss), fused.

``tv_patch(means, prec, densities, extent, grid)`` is ``clgs.fit.losses.tv3d`` of
``clgs.ops.voxelizer.voxelize_precision(means, prec, densities, extent, grid)``: the mean absolute
difference between neighbouring samples of the field, summed over the axes with more than one
sample. It is differentiable wrt means (N, 3), the packed precision (N, 6) and densities (N,) (the
3-sigma half-widths ``extent`` only bound the support), float32 or float64 by the inputs' dtype.

Why fused: for a random 32^3 patch of a 50k-Gaussian scene the kernels' work is small (a few
percent of the Gaussians reach the patch) and the time went to the host: culling with torch ops
over all N rows, gathering and scattering the kept rows through autograd, packing, two blocking
waits, and the TV itself in torch. Here everything from the N rows to the gradient rows of the
kept Gaussians runs on the device in one batch of launches with one wait (``cl/voxelizer.cl``:
``patch_cull``, ``patch_scan``, ``patch_fill``, ``vox_grid``, ``patch_tv``, ``patch_grad``). The
TV's gradient wrt the field is a closed form (signs of the neighbour differences over their
count), so the backward to the Gaussians is computed in the forward for a unit upstream gradient
and the autograd backward only scales the kept rows and scatters them into (N, .) zeros.

Results: the field is bitwise the voxelizer's (same brick lists in Gaussian index order, same
kernel); the TV value and the gradients equal those of ``tv3d`` + the voxelizer's backward to
float rounding (sums of the TV run in another order, and the upstream gradient multiplies the
rows instead of the field's gradient). Same input, same bits, every run.

``patch_tv(backend, tensors, grid)`` is the training loss term's entry: with the OpenCL backend it
reuses the precisions and half-widths that the step's projection built (``Backend._kept``), else
builds them for the Gaussians a ``3 max(scale)`` cube lets reach the block; with the torch
backend it is ``tv3d(backend.voxelize(...))``.
"""
from __future__ import annotations

import math
import threading
import weakref

import numpy as np
import pyopencl as cl
import torch

from clgs.fit.losses import tv3d, tv_count
from clgs.geometry import Grid
from clgs.ops.voxelizer import (
    GRADSTRIDE,
    GSTRIDE,
    SMALL_CELLS,
    Voxelizer,
    columns,
    cov_prec,
    default_voxelizer,
    grid_axes,
    grid_candidates,
    np_dtype,
    voxelize_precision,
    wanted_gradients,
)
from clgs.runtime import round_up
from clgs.errors import InputError

_CHUNK = 512  # Gaussians per culling work-item (at least; at most _MAX_CHUNKS chunks)
_MAX_CHUNKS = 64
_GRAD_ITEMS = 128  # work-items of patch_grad (each takes every 128th kept Gaussian)
_ALIGN = 4096  # host block sections (sub-buffer origins must be aligned)
_lock = threading.Lock()
_runners: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()  # Voxelizer -> its PatchTV


def _tv_weights(shape, dt):
    """(w_x, w_y, w_z): each difference's weight in the TV, 1 / (number of differences over the
    three axes, see ``losses.tv_count``), 0 for an axis of one sample."""

    count = tv_count(shape)
    w = dt(1) / dt(count) if count else dt(0)
    return [w if n > 1 else dt(0) for n in shape[::-1]]


class PatchTV:
    """Runs the fused TV patch on a ``Voxelizer``'s context, queue and programs; owns its pooled
    buffers. Not thread-safe (buffers are reused between calls); use one per thread."""

    def __init__(self, voxelizer: Voxelizer | None = None):
        self.vox = voxelizer or default_voxelizer()
        self._host: dict = {}
        self._cap_list = 1 << 16

    def _host_array(self, name: str, nbytes: int):
        """A pooled page-aligned host byte array of at least ``nbytes`` with a buffer the kernels
        write into (wrapping it on a CPU device; a device buffer copied back otherwise)."""
        entry = self._host.get(name)
        if entry is None or entry[0].size < nbytes:
            size = 1 << max(int(max(nbytes, 1) - 1).bit_length(), 12)
            raw = np.zeros(size + _ALIGN, np.uint8)
            off = -raw.ctypes.data % _ALIGN
            arr = raw[off:off + size]
            if self.vox.io.host_memory:
                buf = cl.Buffer(self.vox.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)
            else:
                buf = cl.Buffer(self.vox.ctx, cl.mem_flags.READ_WRITE, size=size)
            entry = self._host[name] = (arr, buf)
        return entry

    def _outputs(self, sections):
        """One pooled host block for several outputs, so a single map (or copy) brings them all back.
        ``sections``: [(dtype, count)] -> ([arrays], [sub-buffers], block array, block buffer, bytes)."""
        offs, end = [], 0
        for dtype, count in sections:
            offs.append(end)
            end = round_up(end + np.dtype(dtype).itemsize * max(count, 1), _ALIGN)
        arr, buf = self._host_array("out", end)
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
        vox = self.vox
        n = int(means.shape[0])
        nz, ny, nx = (int(s) for s in grid.shape)
        pitch = round_up(nx, 8) + 16
        if n == 0:
            empty = np.zeros((0,), np.int64)
            return (0.0, torch.from_numpy(empty), torch.zeros((0, GRADSTRIDE), dtype=means.dtype) if want else None,
                    torch.zeros(grid.shape, dtype=means.dtype) if field else None)
        prog = vox.program(dt, tuple(sorted(want)))
        ins = [t.detach().contiguous().numpy() for t in (means, prec, densities, extent)]
        bufs = [vox.device_input(a) for a in ins]
        xs, ys, zs = grid_axes(grid, dt)
        nxp = round_up(nx, 8) + 8
        xs_p = np.concatenate([xs, (np.float64(grid.origin[0]) + np.float64(grid.spacing[0])
                                    * np.arange(nx, nxp)).astype(dt)])
        axes = [vox.device_input(a) for a in (xs_p, ys, zs)]
        origin, inv, (nbx, nby, nbz) = vox.brick_cells(grid)
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
        hist = vox.io.scratch("p_hist", 4 * ncells * nchunks)
        count = vox.io.scratch("p_count", 4 * nchunks)
        koff = vox.io.scratch("p_koff", 4 * nchunks)
        kept = vox.io.scratch("p_kept", 4 * n)
        start = vox.io.scratch("p_start", 4 * (ncells + 1))
        packed = vox.io.scratch("p_packed", item * GSTRIDE * n)
        fsize = item * ((nz * ny + 1) * pitch + 16)
        fbuf = vox.io.scratch("p_field", fsize)
        gbuf = vox.io.scratch("p_gout", fsize)
        sections = [(np.int32, 4), (dt, 3 * nz), (np.int32, n)] + ([(dt, n * GRADSTRIDE)] if want else [])
        views, subs, block, block_b, nbytes = self._outputs(sections)
        meta, part, kidx = views[:3]
        meta_b, part_b, kidx_b = subs[:3]
        grad, grad_b = (views[3], subs[3]) if want else (None, None)
        (mb, _), (pb, _), (db, _), (eb, _) = bufs
        (xb, _), (yb, _), (zb, _) = axes
        w = _tv_weights((nz, ny, nx), dt)
        for _attempt in range(3):
            cap = self._cap_list
            lst = vox.io.scratch("p_list", 4 * cap)
            vox.run(prog.kernel("patch_cull"), nchunks, mb, eb, np.int32(n), np.int32(chunk), np.int32(nchunks),
                     *cell_args, *far, slack, hist, count, kept)
            vox.run(prog.kernel("patch_scan"), 1, count, hist, np.int32(nchunks), np.int32(ncells), np.int32(cap),
                     koff, start, meta_b)
            vox.run(prog.kernel("patch_fill"), nchunks, mb, pb, db, eb, np.int32(chunk), np.int32(nchunks),
                     *cell_args, count, kept, koff, hist, meta_b, packed, kidx_b, lst)
            vox.run(prog.kernel("vox_grid"), ncells, packed, start, lst, np.int32(1), xb, yb, zb, np.int32(nx),
                     np.int32(ny), np.int32(nz), np.int32(nbx), np.int32(nby), np.int32(ncells), fbuf,
                     np.int32(pitch), np.int32(8))
            vox.run(prog.kernel("patch_tv"), nz, fbuf, np.int32(nx), np.int32(ny), np.int32(nz), np.int32(pitch),
                     w[0], w[1], w[2], gbuf, part_b)
            if want:
                vox.run(prog.kernel("patch_grad"), _GRAD_ITEMS, packed, meta_b, xb, yb, zb, np.int32(nx),
                         np.int32(ny), np.int32(nz), np.int32(pitch), gbuf, grad_b)
            self.vox.io.fetch([(block_b, block[:nbytes])])  # the one wait
            if not meta[2]:
                break
            pairs = int(meta[1])
            if pairs >= (1 << 31) - 1 or 4 * pairs > vox.ctx.devices[0].max_mem_alloc_size:
                raise MemoryError(
                    f"TV patch: {n} Gaussians meet the patch's {ncells} bricks {pairs} times (too many to list): "
                    "the Gaussians are very large for this patch; bound the scales or use a smaller patch")
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
        rows = torch.from_numpy(grad[:k * GRADSTRIDE].reshape(k, GRADSTRIDE).copy()) if want else None
        out_field = None
        if field:
            fh, fh_b = self._host_array("field", fsize)
            cl.enqueue_copy(vox.queue, fh_b, fbuf, byte_count=fsize)
            self.vox.io.fetch([(fh_b, fh[:fsize])])
            rows_f = fh[:fsize].view(dt)[8:8 + nz * ny * pitch].reshape(nz, ny, pitch)[:, :, :nx]
            out_field = torch.from_numpy(np.ascontiguousarray(rows_f))
        del bufs, axes, ins
        return float(value), idx, rows, out_field


class _TVPatch(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, prec, densities, extent, grid, runner):
        needs = ctx.needs_input_grad[:3]
        value, idx, rows, _ = runner.forward(means, prec, densities, extent, grid, wanted_gradients(needs))
        ctx.n = means.shape[0]
        ctx.idx, ctx.rows = idx, rows
        return means.new_tensor(value)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        needs = ctx.needs_input_grad[:3]
        idx, rows, n = ctx.idx, ctx.rows, ctx.n
        scaled = rows * g
        out = []
        for need, (a, b) in zip(needs, ((0, 3), (3, 9), (9, 10))):
            if not need:
                out.append(None)
                continue
            full = rows.new_zeros((n, b - a))
            full.index_copy_(0, idx, scaled[:, a:b])
            out.append(full if b - a > 1 else full.reshape(n))
        return (*out, None, None, None)


def _runner(voxelizer: Voxelizer | None) -> PatchTV:
    """The ``PatchTV`` of a voxelizer (one each, kept on it, so its pooled buffers live as long)."""
    vox = voxelizer or default_voxelizer()
    with _lock:
        r = _runners.get(vox)
        if r is None:
            r = _runners[vox] = PatchTV(vox)
        return r


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
    Voxelizer._check_grid(grid)
    vox = voxelizer or default_voxelizer()
    _, _, nb = vox.brick_cells(grid)
    if int(np.prod(nb)) > SMALL_CELLS:
        return tv3d(voxelize_precision(means, prec, densities, extent, grid, vox))
    if not (torch.is_grad_enabled() and any(t.requires_grad for t in (means, prec, densities))):
        value = _runner(vox).forward(means, prec, densities, extent, grid)[0]  # no gradient rows
        return means.new_tensor(value)
    return _TVPatch.apply(means, prec, densities, extent.detach(), grid, _runner(vox))


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
