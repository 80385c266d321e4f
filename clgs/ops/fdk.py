"""The FDK/FBP backprojector (``cl/fdk.cl``): voxel-driven, bilinear, with the cone-beam
distance weight; :func:`clgs.ct.fdk.fdk` filters and weights the projections before it."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from clgs.geometry import Geometry
from clgs.ops.operator import Operator
from clgs.runtime import shared


class FDKBackprojector(Operator):
    """Runs ``cl/fdk.cl`` (programs per precision and beam)."""

    SOURCE = "fdk.cl"

    def __call__(self, filtered, geometry: Geometry) -> np.ndarray:
        """Voxel-driven FDK/FBP backprojection (OpenCL) of already filtered, weighted projections.

        float64 input runs the double-precision build; otherwise float32. Returns (Z, Y, X). Work-items
        own eight voxels along z, or along x for volumes thinner than eight slices.
        """
        g = geometry
        if not g.is_circular:
            from clgs.errors import InputError
            raise InputError("the FDK backprojector needs a circular scan; this geometry is given per view as "
                             "vectors (use SART or a Gaussian method)")
        q = np.asarray(filtered)
        dtype = np.float64 if q.dtype == np.float64 else np.float32
        n = g.n_views
        nv, nu = g.nDetector
        nz, ny, nx = g.nVoxel
        nzp = (nz + 7) // 8 * 8
        padded = np.zeros((n, nu + 3, nv + 3), dtype)
        padded[:, 1:nu + 1, 1:nv + 1] = q.transpose(0, 2, 1)
        trig = np.stack([np.cos(g.angles), np.sin(g.angles)], 1).astype(dtype).ravel()
        sp = np.asarray(g.dVoxel[::-1], np.float64)
        c0 = np.asarray(g.offOrigin[::-1], np.float64) - 0.5 * (np.array([nx, ny, nz]) - 1) * sp
        geo = np.array([*c0, *sp, g.DSO, g.DSD, g.dDetector[1], g.dDetector[0], g.offDetector[1],
                        g.offDetector[0], 0.5 * (nu - 1), 0.5 * (nv - 1)], dtype)
        ctx, queue = self.ctx, self.queue
        mf = cl.mem_flags
        q_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=padded)
        t_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=trig)
        g_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=geo)
        real = "double" if dtype == np.float64 else "float"
        prog = self.variant((real, g.mode), {"REAL": real, "CONE": g.mode == "cone"})
        if nz >= 8:  # eight z voxels per work-item
            out = np.empty((nx, ny, nzp), dtype)
            o_buf = cl.Buffer(ctx, mf.WRITE_ONLY, size=out.nbytes)
            prog.kernel("fdk_backproject")(queue, (nzp // 8, ny, nx), None, q_buf, t_buf, o_buf, g_buf, np.int32(n),
                                           np.int32(nx), np.int32(ny), np.int32(nzp), np.int32(nu), np.int32(nv))
            cl.enqueue_copy(queue, out, o_buf)
            return np.ascontiguousarray(out[:, :, :nz].transpose(2, 1, 0))
        nxp = (nx + 7) // 8 * 8  # thin volumes (a single slice): eight x voxels per work-item
        out = np.empty((nz, ny, nxp), dtype)
        o_buf = cl.Buffer(ctx, mf.WRITE_ONLY, size=out.nbytes)
        prog.kernel("fdk_backproject_x")(queue, (nxp // 8, ny, nz), None, q_buf, t_buf, o_buf, g_buf, np.int32(n),
                                         np.int32(nxp), np.int32(ny), np.int32(nu), np.int32(nv))
        cl.enqueue_copy(queue, out, o_buf)
        return np.ascontiguousarray(out[:, :, :nx])


def backproject(filtered, geometry: Geometry) -> np.ndarray:
    """Voxel-driven FDK/FBP backprojection (OpenCL) of already filtered, weighted projections
    (:class:`FDKBackprojector` of the current context)."""
    return shared(FDKBackprojector)(filtered, geometry)
