"""Watertight triangle meshes on grids: inside/outside label, signed distance, exact distance
from points to a mesh. The one implementation behind clgs.anatomy.phantom (CT phantoms), clgs.shape.template
(``mesh_to_label``/``mesh_to_sdf`` in its (Z, Y, X) grid convention) and clgs.mesh.surface
(surface distances).

Grids are :class:`clgs.geometry.Grid` (``shape`` (Z, Y, X), ``origin`` = centre of voxel
[0, 0, 0] as (x, y, z) mm, ``spacing`` (dx, dy, dz) mm). Points and vertices are (x, y, z) mm.
Signed distances are mm, negative inside. NumPy/SciPy only (trimesh for sliver splitting).
"""
from __future__ import annotations

import warnings

import numpy as np

from clgs.errors import InputError
from clgs.io.mesh import check_mesh

__all__ = ["mesh_volume", "mesh_to_label", "point_mesh_distance", "signed_distance", "grid_axes"]


# --------------------------------------------------------------------------------------- grids
def as_grid(grid):
    """Accept a clgs.geometry.Grid or anything with ``.grid()`` (e.g. a Template)."""
    if hasattr(grid, "grid") and callable(grid.grid):
        grid = grid.grid()
    for attr in ("shape", "origin", "spacing"):
        if not hasattr(grid, attr):
            raise TypeError(f"expected a clgs.geometry.Grid (shape, origin, spacing), got {type(grid).__name__}")
    shape = tuple(int(s) for s in grid.shape)
    if len(shape) != 3 or min(shape) < 1:
        raise InputError(f"grid shape must be 3 positive sizes (Z, Y, X), got {grid.shape}")
    spacing = np.asarray(grid.spacing, float)
    if spacing.shape != (3,) or np.any(spacing <= 0) or not np.all(np.isfinite(spacing)):
        raise InputError(f"grid spacing must be 3 positive mm values (dx, dy, dz), got {grid.spacing}")
    return grid


def grid_axes(grid):
    """The voxel-centre coordinates along x, y and z (three 1-D arrays, mm)."""
    nz, ny, nx = grid.shape
    ox, oy, oz = grid.origin
    dx, dy, dz = grid.spacing
    return ox + dx * np.arange(nx), oy + dy * np.arange(ny), oz + dz * np.arange(nz)


# --------------------------------------------------------------------------------------- meshes
def mesh_volume(vertices, faces) -> float:
    """Enclosed volume (mm^3) of a closed, consistently oriented mesh (divergence theorem)."""
    v, f = np.asarray(vertices, float), np.asarray(faces, np.int64)
    tri = v[f]
    return float(abs(np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0))


def mesh_to_label(vertices, faces, grid) -> np.ndarray:
    """Inside (True) / outside of a closed mesh at every voxel centre: bool (Z, Y, X).

    Ray parity along z for every (y, x) column, vectorised over (triangle, column) pairs: each
    crossing toggles the parity of all voxels above it (a prefix sum of toggles). A column that
    passes exactly through an edge or a vertex is counted once by the rasteriser's top-left
    rule, evaluated with bit-identical edge functions on both triangles sharing the edge, so no
    nudging is needed and grid-aligned meshes stay exact."""
    grid = as_grid(grid)
    v, f = check_mesh(vertices, faces, closed=True)
    nz, ny, nx = grid.shape
    ox, oy, oz = grid.origin
    dx, dy, dz = grid.spacing
    u = (v[:, 0] - ox) / dx  # column coordinates in units of voxels
    w = (v[:, 1] - oy) / dy
    a, b, c = f[:, 0].copy(), f[:, 1].copy(), f[:, 2].copy()
    area2 = (u[b] - u[a]) * (w[c] - w[a]) - (w[b] - w[a]) * (u[c] - u[a])
    keep = area2 != 0  # triangles seen edge-on along z cannot be crossed by a z ray
    a, b, c, area2 = a[keep], b[keep], c[keep], area2[keep]
    flip = area2 < 0  # orient every triangle counter-clockwise in the (x, y) plane
    b[flip], c[flip] = c[flip].copy(), b[flip].copy()
    tu = np.stack([u[a], u[b], u[c]], 1)
    tw = np.stack([w[a], w[b], w[c]], 1)
    i0 = np.clip(np.ceil(tu.min(1)), 0, nx).astype(np.int64)
    i1 = np.clip(np.floor(tu.max(1)), -1, nx - 1).astype(np.int64)
    j0 = np.clip(np.ceil(tw.min(1)), 0, ny).astype(np.int64)
    j1 = np.clip(np.floor(tw.max(1)), -1, ny - 1).astype(np.int64)
    ni = np.maximum(i1 - i0 + 1, 0)
    nj = np.maximum(j1 - j0 + 1, 0)
    count = ni * nj
    toggles = np.zeros((nz + 1) * ny * nx, np.int64)
    total = int(count.sum())
    starts = np.cumsum(count) - count
    # process the (triangle, column) pairs in chunks of whole triangles to bound memory
    cuts = np.searchsorted(np.cumsum(count), np.arange(2_000_000, total, 2_000_000), side="left")
    bounds = np.unique(np.concatenate([[0], cuts, [len(a)]]))
    for t_lo, t_hi in zip(bounds[:-1], bounds[1:]):
        sel = np.arange(t_lo, t_hi)
        cnt = count[sel]
        if cnt.sum() == 0:
            continue
        t = np.repeat(sel, cnt)
        local = np.arange(t.size) - np.repeat(starts[sel] - starts[sel[0]], cnt)
        pi = i0[t] + local % np.maximum(ni[t], 1)
        pj = j0[t] + local // np.maximum(ni[t], 1)
        px, py = pi.astype(np.float64), pj.astype(np.float64)
        ta, tb, tc = a[t], b[t], c[t]
        e_bc = _edge(tb, tc, u, w, px, py)  # weight of a
        e_ca = _edge(tc, ta, u, w, px, py)  # weight of b
        e_ab = _edge(ta, tb, u, w, px, py)  # weight of c
        inside = (_owns(e_bc, tb, tc, u, w) & _owns(e_ca, tc, ta, u, w) & _owns(e_ab, ta, tb, u, w))
        if not inside.any():
            continue
        t, pi, pj = t[inside], pi[inside], pj[inside]
        wa, wb, wc = e_bc[inside], e_ca[inside], e_ab[inside]
        zs = (wa * v[a[t], 2] + wb * v[b[t], 2] + wc * v[c[t], 2]) / (wa + wb + wc)
        k = np.clip(np.ceil((zs - oz) / dz), 0, nz).astype(np.int64)
        toggles += np.bincount((k * ny + pj) * nx + pi, minlength=toggles.size)
    toggles = toggles.reshape(nz + 1, ny, nx)
    odd = int(np.count_nonzero(toggles.sum(0) % 2))
    if odd:
        warnings.warn(f"mesh_to_label: {odd} voxel columns cross the surface an odd number of times "
                      "(self-intersecting mesh?); their inside test may be wrong", RuntimeWarning, stacklevel=2)
    return (np.cumsum(toggles, axis=0)[:nz] % 2).astype(bool)


def _edge(p, q, u, w, px, py):
    """Edge function of the directed edge p->q at (px, py), computed in a canonical vertex
    order so that the two triangles sharing an edge get exactly opposite values."""
    lo, hi = np.minimum(p, q), np.maximum(p, q)
    e = (u[hi] - u[lo]) * (py - w[lo]) - (w[hi] - w[lo]) * (px - u[lo])
    return np.where(p == lo, e, -e)


def _owns(e, p, q, u, w):
    """Top-left rule: a point on edge p->q of a counter-clockwise triangle belongs to it when the
    edge points down (dy < 0), or is horizontal pointing left."""
    ddx = u[q] - u[p]
    ddy = w[q] - w[p]
    return (e > 0) | ((e == 0) & ((ddy < 0) | ((ddy == 0) & (ddx < 0))))


def point_mesh_distance(points, vertices, faces, k: int = 16, chunk: int = 1024) -> np.ndarray:
    """Unsigned Euclidean distance (mm) from points (N, 3) to a triangle mesh, exact.

    An upper bound U (squared) comes from the ``k`` triangles with the nearest centroids
    (KD-tree). Then a coarse-to-fine search over a bounding-box hierarchy proves that no other
    triangle is closer: triangles sorted along a Morton (Z-order) curve of their centroids form
    blocks of 8, 64, 512, ... consecutive triangles, each with its axis-aligned bounding box; a
    block is opened only while its box is within U of the point. A far point (from a streaky
    surface, say) then opens the few blocks that face it instead of every triangle. The distance
    to each candidate is exact (the plane when the foot is inside the triangle, else the nearest
    edge). Edges longer than 4 times the median are split first (the surface is the same), so
    that a few long slivers do not widen the boxes."""
    from scipy.spatial import cKDTree

    v, f = np.asarray(vertices, float), np.asarray(faces, np.int64)
    pts = np.asarray(points, float).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise InputError(f"point_mesh_distance needs faces (F>=1, 3), got shape {f.shape}")
    tri = v[f]
    edges = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=-1)
    limit = 4.0 * float(np.median(edges))
    if limit > 0 and edges.max() > limit:
        import trimesh

        # split long slivers (same surface, same distances) so that their boxes stay small
        v, f = trimesh.remesh.subdivide_to_size(v, f, max_edge=limit, max_iter=16)[:2]
        tri = v[f]
    centroid = tri.mean(1)
    levels = _box_levels(tri, centroid)
    tree = cKDTree(centroid)
    k = int(max(1, min(k, len(f))))
    out = np.empty(len(pts))
    for s in range(0, len(pts), chunk):
        p = pts[s:s + chunk]
        _, idx = tree.query(p, k=k)
        best = _tri_d2(p, tri[idx.reshape(len(p), k)]).min(1)
        if k < len(f):
            lo, hi = levels[-1]
            pi = np.repeat(np.arange(len(p)), len(lo))
            bi = np.tile(np.arange(len(lo)), len(p))
            for depth in range(len(levels) - 1, -1, -1):
                lo, hi = levels[depth]
                gap = np.maximum(np.maximum(lo[bi] - p[pi], p[pi] - hi[bi]), 0.0)
                keep = np.einsum("ij,ij->i", gap, gap) <= best[pi]  # the box may hold a closer triangle
                pi, bi = pi[keep], bi[keep]
                if depth == 0 or pi.size == 0:
                    break
                n_next = len(levels[depth - 1][0])
                pi = np.repeat(pi, 8)
                bi = (8 * bi[:, None] + np.arange(8)).reshape(-1)
                ok = bi < n_next
                pi, bi = pi[ok], bi[ok]
            if pi.size:
                t = levels.order[bi]
                d2 = _tri_d2(p[pi], tri[t][:, None])[:, 0]
                np.minimum.at(best, pi, d2)
        out[s:s + chunk] = np.sqrt(best)
    return out


class _Levels(list):
    """Bounding boxes (lo, hi) of the triangles (level 0, in ``order``) and of blocks of 8, 64, ...
    consecutive ones along the Morton curve (levels 1, 2, ...; the last has at most 64 boxes)."""

    order: np.ndarray


def _box_levels(tri, centroid) -> _Levels:
    lo_c, hi_c = centroid.min(0), centroid.max(0)
    q = ((centroid - lo_c) / np.maximum(hi_c - lo_c, 1e-12) * 1023).astype(np.int64)
    code = np.zeros(len(tri), np.int64)
    for bit in range(10):  # interleave the 10-bit x, y, z cells into a 30-bit Morton code
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    order = np.argsort(code, kind="stable")
    lo, hi = tri[order].min(1), tri[order].max(1)
    levels = _Levels([(lo, hi)])
    levels.order = order
    while len(lo) > 64:
        starts = np.arange(0, len(lo), 8)
        lo, hi = np.minimum.reduceat(lo, starts, axis=0), np.maximum.reduceat(hi, starts, axis=0)
        levels.append((lo, hi))
    return levels


def _tri_d2(p, tri):
    """Squared distance from points p (N, 3) to triangles tri (N, K, 3 corners, 3)."""
    A, B, C = tri[:, :, 0], tri[:, :, 1], tri[:, :, 2]
    q = p[:, None, :]
    d2 = np.minimum(np.minimum(_seg_d2(q, A, B), _seg_d2(q, B, C)), _seg_d2(q, C, A))
    n = np.cross(B - A, C - A)
    nn = np.einsum("...i,...i->...", n, n)
    ok = nn > 0
    nn_safe = np.where(ok, nn, 1.0)
    h = np.einsum("...i,...i->...", q - A, n)
    foot = q - (h / nn_safe)[..., None] * n
    # the foot is inside when it lies on the inner side of all three edges
    s1 = np.einsum("...i,...i->...", np.cross(B - A, foot - A), n)
    s2 = np.einsum("...i,...i->...", np.cross(C - B, foot - B), n)
    s3 = np.einsum("...i,...i->...", np.cross(A - C, foot - C), n)
    inside = ok & (s1 >= 0) & (s2 >= 0) & (s3 >= 0)
    return np.where(inside, np.minimum(d2, h * h / nn_safe), d2)


def _seg_d2(q, a, b):
    ab = b - a
    den = np.einsum("...i,...i->...", ab, ab)
    t = np.clip(np.einsum("...i,...i->...", q - a, ab) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    d = q - (a + t[..., None] * ab)
    return np.einsum("...i,...i->...", d, d)


def signed_distance(shape, grid, band_voxels: float = 1.5, label=None) -> np.ndarray:
    """Signed distance (float32 mm, negative inside) on ``grid``.

    ``shape`` is a bool label volume (Z, Y, X) or a closed mesh ``(vertices, faces)``. From a
    label: Euclidean distance transforms of the inside and the outside (scipy), shifted by half
    a voxel so that the zero level lies between the voxel centres on either side of the
    boundary (accurate to about half a voxel). From a mesh: the same, and within
    ``band_voxels`` of the surface the exact distance to the triangles, with the sign of the
    mesh's inside test (``label``: that inside on ``grid``, when already computed)."""
    from scipy.ndimage import distance_transform_edt

    grid = as_grid(grid)
    mesh = None
    if isinstance(shape, (tuple, list)) and len(shape) == 2:
        mesh = check_mesh(*shape, closed=True)
        if label is None:
            label = mesh_to_label(mesh[0], mesh[1], grid)
    else:
        label = shape
    label = np.asarray(label).astype(bool)
    if label.shape != tuple(grid.shape):
        raise InputError(f"label shape {label.shape} does not match the grid {tuple(grid.shape)}")
    if not label.any():
        raise InputError("nothing is inside: the shape misses every voxel centre (is it inside the grid, "
                         "and larger than a voxel?)")
    if label.all():
        raise InputError("everything is inside: the grid lies within the shape; enlarge the grid")
    sampling = tuple(float(s) for s in grid.spacing[::-1])  # (dz, dy, dx)
    h = min(sampling)
    d_in = distance_transform_edt(label, sampling=sampling)
    d_out = distance_transform_edt(~label, sampling=sampling)
    sdf = np.where(label, -(d_in - 0.5 * h), d_out - 0.5 * h)
    if mesh is not None:
        band = np.abs(sdf) <= band_voxels * max(sampling)
        kk, jj, ii = np.nonzero(band)
        xs, ys, zs = grid_axes(grid)
        pts = np.stack([xs[ii], ys[jj], zs[kk]], 1)
        import trimesh

        # split long slivers (same surface, same distances) so that their boxes stay small
        fine = trimesh.remesh.subdivide_to_size(mesh[0], mesh[1], max_edge=1.5 * h, max_iter=12)
        d = point_mesh_distance(pts, fine[0], fine[1])
        sdf[band] = np.where(label[band], -d, d)
    return sdf.astype(np.float32)
