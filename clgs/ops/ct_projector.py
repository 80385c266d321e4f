"""Voxel-volume X-ray projector and its exact adjoint (a matched pair, for SART and simulation).

Forward model: Joseph's method. Each detector pixel's ray (the conventions of
:mod:`clgs.geometry`: cone rays from the source through the pixel centre, ``t > 0`` only;
parallel rays through the pixel centre along ``-e_s``) steps through the voxel-centre planes of
its main in-plane axis (x when the ray is closer to x than to y in voxel units, else y). On each
plane the volume is interpolated bilinearly in the other two axes and weighted by the ray's
length between planes, so a ray through a uniform region of value ``mu`` (per mm) gives
``mu * chord length (mm)``. Voxels outside the grid are zero.

Adjoint: the backprojector evaluates the same weights from each voxel's side (a gather over the
detector columns whose rays can reach it), so ``<A x, y> = <x, A^T y>`` up to rounding, with no
atomics and bitwise-reproducible results.

The kernels work in voxel-index coordinates; ``views`` are converted on the host. They take any
per-view geometry whose detector rows are horizontal and columns along z (any source position,
detector offset, turn about the columns); a rolled or pitched detector goes through an upright
virtual detector and a sparse resampling (:mod:`clgs.ops.ct_upright`). Because the detector's v
axis is z, rays never step along z; for cone angles steeper than 45 degrees in voxel units (thin
slices with a huge cone) z would be undersampled, and a warning says so.
"""
from __future__ import annotations

import warnings

import numpy as np

from clgs.errors import InputError
from clgs.geometry import Geometry
from clgs.ops.ct_upright import tilted_views, upright_stand_in
from clgs.runtime import Operator

_VIEW_STRIDE = 16
_ZB = 32  # z voxels per backprojector work-item (cl/ct_backprojector.cl)


def _as_real(array, name):
    """float32 unless the caller gave float64 (which selects the double-precision kernels)."""
    arr = np.asarray(array)
    if arr.dtype != np.float64:
        arr = arr.astype(np.float32, copy=False)
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise InputError(f"{name} contains {bad} NaN or Inf value(s); clean the input before projecting")
    return arr


def _round8(n):
    return (int(n) + 7) // 8 * 8


BACKWARD_SOURCE = "ct_backprojector.cl"  # the transpose, built on the forward's file


class CTProjector(Operator):
    """Matched forward projector / backprojector for one :class:`~clgs.geometry.Geometry`.

    ``forward(volume)`` takes a (Z, Y, X) volume in values per mm and returns (n_views, V, U)
    line integrals; ``backward(projections)`` is its exact transpose. Both accept ``views`` (a
    sequence of view indices) to work on a subset, as OS-SART does. float64 inputs run the
    double-precision build (for tests); anything else runs in float32. Programs are compiled once
    per variant (cone/parallel, precision) and cached by :mod:`clgs.runtime`; device buffers are
    kept and reused between calls. ``ctx``/``queue``: where it runs (default: the process's device).
    """

    SOURCE = "ct_projector.cl"
    _views_all: np.ndarray  # (n_views, 16) view records (see _index_views)

    def __init__(self, geometry: Geometry, ctx=None, queue=None):
        if not isinstance(geometry, Geometry):
            raise TypeError(f"CTProjector needs a clgs.geometry.Geometry, got {type(geometry).__name__}")
        super().__init__(ctx, queue)
        self.geometry = geometry
        self.cone = geometry.mode == "cone"
        nz, ny, nx = geometry.nVoxel
        self.shape = (nz, ny, nx)
        self.spacing_xyz = np.asarray(geometry.dVoxel[::-1], np.float64)
        self._view_cache: dict = {}
        self._upright = None
        if np.any(tilted_views(geometry)):  # a rolled or pitched detector: see clgs.ops.ct_upright
            virtual, mats = upright_stand_in(geometry, _round8(geometry.nDetector[0]))
            self._upright = (CTProjector(virtual, self.ctx, self.queue), mats)
            self._views_all = self._upright[0]._views_all  # view indices check against these
            return
        self._views_all = self._index_views()
        self._check_geometry()

    # ------------------------------------------------------------------------------ set-up
    def _index_views(self) -> np.ndarray:
        """(n_views, 16) float64 view records in voxel-index coordinates (see cl/ct_projector.cl and
        cl/ct_backprojector.cl)."""
        g = self.geometry
        nz, ny, nx = g.nVoxel
        sp = self.spacing_xyz
        c0 = g.centre_xyz - 0.5 * (np.array([nx, ny, nz]) - 1) * sp  # world mm, as the vectors
        vv = g.view_vectors(scene=False)
        nv, nu = g.nDetector
        us, vs = vv[:, 6:9], vv[:, 9:12]
        if np.any(tilted_views(g)):  # __init__ sends these through an upright stand-in
            raise InputError("the voxel projector's kernels need horizontal detector rows and columns along z")
        p0 = vv[:, 3:6] - 0.5 * (nu - 1) * us - 0.5 * (nv - 1) * vs  # centre of pixel (0, 0)
        to_idx = lambda p: (p - c0) / sp  # noqa: E731
        us_i, vs_i = us / sp, vs / sp
        out = np.zeros((g.n_views, _VIEW_STRIDE), np.float64)
        dmax = float(max(sp[0], sp[1]))  # mm from a voxel centre to the far ends of its segments
        if self.cone:
            s_i = to_idx(vv[:, 0:3])
            d0 = to_idx(p0) - s_i
            out[:, 0:2] = s_i[:, :2]
            out[:, 4:6] = d0[:, :2]
            out[:, 6:8] = us_i[:, :2]
            out[:, 8] = s_i[:, 2]
            out[:, 10] = d0[:, 2]
            out[:, 11] = vs_i[:, 2]
            # nearest depth of any point within a voxel of the grid, and the widest fan angle
            # per view, in the plane: n the detector normal, depth along n
            half = 0.5 * np.hypot((nx + 2) * sp[0], (ny + 2) * sp[1])
            centre = g.centre_xyz[:2]  # world mm, as the vectors
            du = np.hypot(us[:, 0], us[:, 1])
            eu = us[:, :2] / du[:, None]
            normal = np.stack([eu[:, 1], -eu[:, 0]], 1)
            src = vv[:, 0:2]
            dsd = np.abs(np.sum((vv[:, 3:5] - src) * normal, 1))
            depth_min = np.abs(np.sum((centre - src) * normal, 1)) - half
            if np.any(depth_min <= 0):
                i = int(np.argmin(depth_min))
                raise InputError(f"view {i}: the volume (grown by one voxel) reaches the source's depth along the "
                                 "detector normal: move the source away or turn the detector to face it")
            ends = p0[:, :2, None] + np.array([0.0, nu - 1.0])[None, None, :] * us[:, :2, None] - src[:, :, None]
            reach = np.max(np.abs(np.sum(ends * eu[:, :, None], 1)), 1) + 0.5 * du
            tan_max = np.maximum(half / depth_min + np.abs(np.sum((centre - src) * eu, 1)) / depth_min, reach / dsd)
            out[:, 12] = dmax * dsd / depth_min * np.sqrt(1 + tan_max**2) / du * 1.01 + 1e-3
            delta = dmax / depth_min
            out[:, 13] = delta / (1 - delta) * 1.01 + 1e-6
            out[:, 14] = 1.0 / out[:, 11]
            out[:, 15] = out[:, 4] * out[:, 7] - out[:, 5] * out[:, 6]  # cross(b0, bu)
        else:
            r_i = vv[:, 0:3] / sp
            p0_i = to_idx(p0)
            out[:, 0:2] = p0_i[:, :2]
            out[:, 2:4] = us_i[:, :2]
            out[:, 4:6] = r_i[:, :2]
            out[:, 8] = p0_i[:, 2]
            out[:, 9] = vs_i[:, 2]
            out[:, 10] = r_i[:, 2]
            out[:, 12] = dmax / np.hypot(us[:, 0], us[:, 1]) * 1.01 + 1e-3
            out[:, 14] = 1.0 / out[:, 9]
            out[:, 15] = 1.0 / (out[:, 2] * out[:, 5] - out[:, 3] * out[:, 4])  # 1 / cross(au, b0)
        return out

    def _check_geometry(self):
        g = self.geometry
        nz, ny, nx = g.nVoxel
        w = self._views_all
        if self.cone:
            # the backprojector finds a voxel's detector columns from the corners of the square
            # one voxel around it: the source must stay outside the grid grown by one voxel
            half = 0.5 * np.hypot((nx + 2) * self.spacing_xyz[0], (ny + 2) * self.spacing_xyz[1])
            centre = np.array([(nx - 1) / 2, (ny - 1) / 2])
            dist = np.hypot(*((w[:, 0:2] - centre) * self.spacing_xyz[:2]).T)
            if np.any(dist <= half):
                raise InputError(
                    f"the source orbit (closest {dist.min():.1f} mm from the volume centre) passes within "
                    f"the volume grown by one voxel (half-diagonal {half:.1f} mm): increase DSO"
                )
            nv, nu = g.nDetector
            uu, vv = np.meshgrid([0.0, nu - 1.0], [0.0, nv - 1.0])
            uu, vv = uu.ravel()[None], vv.ravel()[None]
            dx = np.abs(w[:, 4:5] + uu * w[:, 6:7])
            dy = np.abs(w[:, 5:6] + uu * w[:, 7:8])
            dz = np.abs(w[:, 10:11] + vv * w[:, 11:12])
            steep = float(np.max(dz / np.maximum(np.maximum(dx, dy), 1e-300)))
            if steep > 1.0:
                warnings.warn(
                    "some rays are steeper than 45 degrees in voxel units; Joseph's method steps along x or y "
                    "only, so z is sampled more coarsely than one voxel there", stacklevel=3)

    def _program(self, dtype, kind):
        real = "double" if dtype == np.float64 else "float"
        source = self.SOURCE if kind == "forward" else BACKWARD_SOURCE
        return self.variant((real, kind), {"REAL": real, "CONE": self.cone}, source)

    def _views(self, views, dtype):
        if views is None:
            key: tuple = (None, np.dtype(dtype).str)
            idx = None
        else:
            idx = np.asarray(views, dtype=np.int64).reshape(-1)
            if idx.size == 0:
                raise InputError("views is empty: give at least one view index")
            if idx.min() < 0 or idx.max() >= self.geometry.n_views:
                raise InputError(f"view indices must lie in [0, {self.geometry.n_views}), got {idx.min()}..{idx.max()}")
            key = (idx.tobytes(), np.dtype(dtype).str)
        hit = self._view_cache.get(key)
        if hit is None:
            rec = self._views_all if idx is None else self._views_all[idx]
            arr = np.ascontiguousarray(rec, dtype=dtype)
            if len(self._view_cache) > 4096:
                self._view_cache.clear()
            hit = self._view_cache[key] = (arr, self.io.constant(arr))
        return hit

    def _column_table(self, views, dtype, vbuf, n, prog):
        """Device table of each view's per-column ray set-up (kernel ct_columns), cached."""
        key = ("columns", None if views is None else np.asarray(views, np.int64).tobytes(), np.dtype(dtype).str)
        hit = self._view_cache.get(key)
        if hit is None:
            nu = self.geometry.nDetector[1]
            hit = self.io.new(n * nu * 8 * np.dtype(dtype).itemsize)
            self.launch(prog, "ct_columns", (nu, n), None, vbuf, hit, np.int32(nu))
            self._view_cache[key] = hit
        return hit

    def _ray_scale(self, views, dtype):
        """(n, U, Vp) length in mm of each ray's direction vector D (cone: pixel - source), which
        turns steps in the ray parameter into millimetres; 1 for parallel beam; 0 in padded rows."""
        key = ("scale", None if views is None else np.asarray(views, np.int64).tobytes(), np.dtype(dtype).str)
        hit = self._view_cache.get(key)
        if hit is None:
            rec = self._views_all if views is None else self._views_all[np.asarray(views, np.int64)]
            nv, nu = self.geometry.nDetector
            hit = np.zeros((rec.shape[0], nu, _round8(nv)), dtype)
            if not self.cone:
                hit[:, :, :nv] = 1.0
            else:
                u = np.arange(nu, dtype=np.float64)[None, :, None]
                v = np.arange(nv, dtype=np.float64)[None, None, :]
                sx, sy, sz = self.spacing_xyz
                dx = (rec[:, 4, None, None] + u * rec[:, 6, None, None]) * sx
                dy = (rec[:, 5, None, None] + u * rec[:, 7, None, None]) * sy
                dz = (rec[:, 10, None, None] + v * rec[:, 11, None, None]) * sz
                hit[:, :, :nv] = np.sqrt(dx * dx + dy * dy + dz * dz)
            self._view_cache[key] = hit
        return hit

    # ------------------------------------------------------------------------------ public
    @property
    def n_views(self) -> int:
        return self.geometry.n_views

    def forward(self, volume, views=None) -> np.ndarray:
        """Line integrals (n_views, V, U) of ``volume`` (Z, Y, X), values per mm -> value x mm."""
        vol = _as_real(volume, "volume")
        if vol.shape != self.shape:
            raise InputError(f"volume has shape {vol.shape}, the geometry expects nVoxel (Z, Y, X) = {self.shape}")
        nv = self.geometry.nDetector[0]
        padded = self.pad_volume(vol)
        return np.ascontiguousarray(self.forward_padded(padded, views)[:, :, :nv].transpose(0, 2, 1))

    def backward(self, projections, views=None) -> np.ndarray:
        """The exact transpose of :meth:`forward`: (n_views, V, U) -> volume (Z, Y, X)."""
        proj = _as_real(projections, "projections")
        dtype = proj.dtype.type
        n = self._views(views, dtype)[0].shape[0]  # also checks the view indices
        nv, nu = self.geometry.nDetector
        if proj.ndim == 2 and n == 1:
            proj = proj[None]
        if proj.shape != (n, nv, nu):
            raise InputError(
                f"projections have shape {proj.shape}, expected (n_views, V, U) = {(n, nv, nu)} for these views")
        tp = np.zeros((n, nu, _round8(nv)), dtype)
        tp[:, :, :nv] = proj.transpose(0, 2, 1)
        nz = self.shape[0]
        return np.ascontiguousarray(self.backward_internal(tp, views)[:, :, :nz].transpose(2, 1, 0))

    # ------------------------------------------------------------------------------ internal layouts
    # The kernels' own layouts, for iterative methods that keep their arrays in them (no transposes):
    # volume padded (X + 3, Y + 3, Z + 3) with the voxel [k, j, i] at [i + 1, j + 1, k + 1];
    # projections (n, U, V rounded up to 8) with row v fastest; backprojection (X, Y, Z rounded up).

    def pad_volume(self, volume) -> np.ndarray:
        """(Z, Y, X) -> the forward kernel's zero-padded (X + 3, Y + 3, Z + 3) layout."""
        nz, ny, nx = self.shape
        padded = np.zeros((nx + 3, ny + 3, nz + 3), volume.dtype)
        padded[1:nx + 1, 1:ny + 1, 1:nz + 1] = volume.transpose(2, 1, 0)
        return padded

    def _view_list(self, views):
        return range(self.geometry.n_views) if views is None else np.asarray(views, np.int64).reshape(-1)

    def forward_padded(self, padded, views=None) -> np.ndarray:
        """Forward projection of a padded volume (see :meth:`pad_volume`): (n, U, Vp) float array."""
        if self._upright is not None:
            P, mats = self._upright
            virtual = P.forward_padded(padded, views)
            nv, nu = self.geometry.nDetector
            out = np.empty((virtual.shape[0], nu, _round8(nv)), virtual.dtype)
            for k, i in enumerate(self._view_list(views)):
                out[k] = (mats[i] @ virtual[k].ravel()).reshape(nu, -1)
            return out
        dtype = np.float64 if padded.dtype == np.float64 else np.float32
        padded = np.ascontiguousarray(padded, dtype)
        nz, ny, nx = self.shape
        if padded.shape != (nx + 3, ny + 3, nz + 3):
            raise InputError(f"padded volume has shape {padded.shape}, expected {(nx + 3, ny + 3, nz + 3)}")
        with self.call() as io:
            rec, vbuf = self._views(views, dtype)
            nv, nu = self.geometry.nDetector
            nvp = _round8(nv)
            n = rec.shape[0]
            out = np.empty((n, nu, nvp), dtype)
            prog = self._program(dtype, "forward")
            sx, sy, sz = (dtype(s) for s in self.spacing_xyz)
            vol_buf = io.input(padded, "vol_in")
            out_buf = io.output(out, "proj_out")
            self.launch(prog, "ct_forward", (nvp // 8, nu, n), None, vol_buf, vbuf, out_buf, np.int32(nx),
                        np.int32(ny), np.int32(nz), np.int32(nu), np.int32(nvp), sx, sy, sz)
            io.fetch([(out_buf, out)])
        return out

    def backward_internal(self, tp, views=None) -> np.ndarray:
        """Transpose of :meth:`forward_padded`: (n, U, Vp) projections -> (X, Y, Zp) volume.

        Rows v >= V of ``tp`` are ignored.
        """
        if self._upright is not None:
            P, mats = self._upright
            n = self._views(views, tp.dtype.type)[0].shape[0]
            nv, nu = self.geometry.nDetector
            if tp.shape != (n, nu, _round8(nv)):
                raise InputError(f"projections in kernel layout have shape {tp.shape}, expected {(n, nu, _round8(nv))}")
            nv2, nu2 = P.geometry.nDetector
            virtual = np.empty((n, nu2, _round8(nv2)), tp.dtype)
            for k, i in enumerate(self._view_list(views)):
                virtual[k] = (mats[i].T @ tp[k].ravel()).reshape(nu2, -1)
            return P.backward_internal(virtual, views)
        dtype = np.float64 if tp.dtype == np.float64 else np.float32
        with self.call() as io:
            rec, vbuf = self._views(views, dtype)
            n = rec.shape[0]
            nv, nu = self.geometry.nDetector
            nvp = _round8(nv)
            if tp.shape != (n, nu, nvp):
                raise InputError(f"projections in kernel layout have shape {tp.shape}, expected {(n, nu, nvp)}")
            nz, ny, nx = self.shape
            nzp = (nz + _ZB - 1) // _ZB * _ZB
            scaled = np.empty((n, nu, nvp), dtype)
            np.multiply(tp, self._ray_scale(views, dtype), out=scaled)
            prog = self._program(dtype, "backward")
            out = np.empty((nx, ny, nzp), dtype)
            t_buf = self._column_table(views, dtype, vbuf, n, prog)
            p_buf = io.input(scaled, "proj_in")
            out_buf = io.output(out, "vol_out")
            self.launch(prog, "ct_backward", (nzp // _ZB, ny, nx), None, p_buf, vbuf, t_buf, out_buf, np.int32(n),
                        np.int32(nx), np.int32(ny), np.int32(nz), np.int32(nzp), np.int32(nu), np.int32(nv),
                        np.int32(nvp))
            io.fetch([(out_buf, out)])
        return out
