"""The FDK/FBP backprojector (``cl/fdk.cl``): voxel-driven, bilinear, with the cone-beam
distance weight; :func:`clgs.ct.fdk.fdk` filters and weights the projections before it.

A circular scan runs the kernels that turn each voxel by the view's angle; a per-view (vector)
scan runs one that takes each view's 3 x 4 projection matrix (:func:`projection_matrices`), built
from the view's own source, detector centre and pixel steps."""
from __future__ import annotations

import numpy as np

from clgs.geometry import Geometry
from clgs.runtime import Operator, shared


class FDKBackprojector(Operator):
    """Runs ``cl/fdk.cl`` (an :class:`~clgs.runtime.Operator`: programs per precision and beam,
    pooled buffers, one call at a time)."""

    SOURCE = "fdk.cl"

    def _program(self, dtype, mode: str):
        real = "double" if dtype == np.float64 else "float"
        return self.variant((real, mode), {"REAL": real, "CONE": mode == "cone"})

    def __call__(self, filtered, geometry: Geometry) -> np.ndarray:
        """Voxel-driven FDK/FBP backprojection (OpenCL) of already filtered, weighted projections.

        float64 input runs the double-precision build; otherwise float32. Returns (Z, Y, X). Work-items
        own eight voxels along z, or along x for volumes thinner than eight slices.
        """
        g = geometry
        q = np.asarray(filtered)
        if not g.is_circular:
            return self._vectors(q, g)
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
        prog = self._program(dtype, g.mode)
        with self.call() as io:
            q_buf, t_buf, g_buf = io.input(padded, "proj"), io.input(trig, "trig"), io.input(geo, "geo")
            if nz >= 8:  # eight z voxels per work-item
                out = np.empty((nx, ny, nzp), dtype)
                o_buf = io.output(out, "out")
                self.launch(prog, "fdk_backproject", (nzp // 8, ny, nx), None, q_buf, t_buf, o_buf, g_buf,
                            np.int32(n), np.int32(nx), np.int32(ny), np.int32(nzp), np.int32(nu), np.int32(nv))
                io.fetch([(o_buf, out)])
                return np.ascontiguousarray(out[:, :, :nz].transpose(2, 1, 0))
            nxp = (nx + 7) // 8 * 8  # thin volumes (a single slice): eight x voxels per work-item
            out = np.empty((nz, ny, nxp), dtype)
            o_buf = io.output(out, "out")
            self.launch(prog, "fdk_backproject_x", (nxp // 8, ny, nz), None, q_buf, t_buf, o_buf, g_buf, np.int32(n),
                        np.int32(nxp), np.int32(ny), np.int32(nu), np.int32(nv))
            io.fetch([(o_buf, out)])
        return np.ascontiguousarray(out[:, :, :nx])

    def _vectors(self, q: np.ndarray, g: Geometry) -> np.ndarray:
        """The per-view kernel: eight lanes along z, or along x for volumes thinner than eight slices."""
        dtype = np.float64 if q.dtype == np.float64 else np.float32
        nv, nu = g.nDetector
        nz, ny, nx = g.nVoxel
        padded = np.zeros((g.n_views, nu + 3, nv + 3), dtype)
        padded[:, 1:nu + 1, 1:nv + 1] = q.transpose(0, 2, 1)
        mats = projection_matrices(g).astype(dtype)
        lo, _ = g.volume_bounds()
        sp = np.asarray(g.dVoxel[::-1], np.float64)
        p0 = lo + 0.5 * sp
        ex, ey, ez = np.diag(sp)
        if nz >= 8:  # lanes along z, then y, x: out (nX, nY, nZp)
            n_lane, n1, n2, axes = nz, ny, nx, (ez, ey, ex)
        else:  # lanes along x, then y, z: out (nZ, nY, nXp)
            n_lane, n1, n2, axes = nx, ny, nz, (ex, ey, ez)
        nlp = (n_lane + 7) // 8 * 8
        geo = np.concatenate([p0, *axes]).astype(dtype)
        prog = self._program(dtype, g.mode)
        out = np.empty((n2, n1, nlp), dtype)
        with self.call() as io:
            q_buf, g_buf = io.input(padded, "proj"), io.input(geo, "geo")
            m_buf = io.input(np.ascontiguousarray(mats.ravel()), "mats")
            o_buf = io.output(out, "out")
            self.launch(prog, "fdk_backproject_vec", (nlp // 8, n1, n2), None, q_buf, m_buf, o_buf, g_buf,
                        np.int32(g.n_views), np.int32(nlp), np.int32(n1), np.int32(nu), np.int32(nv))
            io.fetch([(o_buf, out)])
        out = out[:, :, :n_lane]
        return np.ascontiguousarray(out.transpose(2, 1, 0) if nz >= 8 else out)


def view_depths(geometry: Geometry):
    """Per view, in the scanner's frame: (unit detector normals pointing from the source to the
    detector (n, 3), source-detector distances ``D`` along them (n,), reference depths (n,): the
    source's depth of the frame's origin along the normal, or ``D`` where the origin lies at or
    behind the source). Parallel beam: the ray directions, ones, ones."""
    vec = geometry.frame_vectors()
    if geometry.mode != "cone":
        return vec[:, 0:3] / np.linalg.norm(vec[:, 0:3], axis=1, keepdims=True), np.ones(len(vec)), np.ones(len(vec))
    normal = np.cross(vec[:, 6:9], vec[:, 9:12])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    dist = np.sum(normal * (vec[:, 3:6] - vec[:, 0:3]), 1)
    normal *= np.where(dist < 0, -1.0, 1.0)[:, None]
    dist = np.abs(dist)
    ref = -np.sum(normal * vec[:, 0:3], 1)
    return normal, dist, np.where(ref > 1e-6 * dist, ref, dist)


def projection_matrices(geometry: Geometry) -> np.ndarray:
    """(n_views, 3, 4) float64: each view's projection matrix, mm in the scanner's frame (that of
    :meth:`Geometry.frame_vectors`) to padded detector coordinates, as ``cl/fdk.cl`` reads them.

    ``P @ (x, y, z, 1) = (u' w, v' w, w)`` with ``u' = iu + 1``, ``v' = iv + 1`` the point's
    (fractional) pixel column and row plus one. Cone beam: ``w`` is the point's depth from the source
    along the detector normal over that of the frame's origin (the isocentre: DSO for a circular
    scan; the source-detector distance where the origin lies at or behind the source), so the
    kernel's distance weight ``1 / w^2`` is the circular ``(DSO / depth)^2``; parallel beam:
    ``w = 1``. Pixel coordinates use the dual basis of the u and v steps, exact even for steps that
    are not quite perpendicular."""
    vec = geometry.frame_vectors()
    nv, nu = geometry.nDetector
    centre = np.array([0.5 * (nu - 1) + 1.0, 0.5 * (nv - 1) + 1.0])
    s, d, steps = vec[:, 0:3], vec[:, 3:6], vec[:, 6:12].reshape(-1, 2, 3)
    gram = steps @ steps.transpose(0, 2, 1)
    dual = np.linalg.solve(gram, steps)  # (n, 2, 3): (h - d) . dual[:, 0] = column offset of h
    out = np.zeros((len(vec), 3, 4))
    if geometry.mode == "cone":
        normals, dists, refs = view_depths(geometry)
        nw = normals / refs[:, None]  # w = nw . (x - s)
        k = centre + np.einsum("nj,nij->ni", s - d, dual)  # u' w = k w + (D / ref) dual . (x - s)
        lin = (dists / refs)[:, None, None] * dual
        out[:, :2, :3] = lin + k[:, :, None] * nw[:, None, :]
        out[:, :2, 3] = -np.einsum("nij,nj->ni", lin, s) - k * np.sum(nw * s, 1)[:, None]
        out[:, 2, :3] = nw
        out[:, 2, 3] = -np.sum(nw * s, 1)
    else:
        out[:, :2, :3] = dual
        out[:, :2, 3] = centre - np.einsum("nij,nj->ni", dual, d)
        out[:, 2, 3] = 1.0
    return out


def backproject(filtered, geometry: Geometry) -> np.ndarray:
    """Voxel-driven FDK/FBP backprojection (OpenCL) of already filtered, weighted projections
    (:class:`FDKBackprojector` of the current context)."""
    return shared(FDKBackprojector)(filtered, geometry)
