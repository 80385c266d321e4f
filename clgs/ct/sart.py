"""SART and OS-SART with the matched voxel projector pair.

Update for one subset ``S`` of views (all views when ``subsets == 1``, which is SART):

    x <- x + relaxation * (A_S^T ((b_S - A_S x) / (A_S 1))) / (A_S^T 1)

with ``A`` the forward projector of :class:`clgs.ops.ct_projector.CTProjector` and ``A^T`` its exact
transpose: ``A 1`` are the ray lengths through the volume (row sums), ``A_S^T 1`` the column sums
of the subset. Rays that barely touch the volume (row sum below 1e-6 of the largest) and voxels no
ray of the subset reaches are left out, so nothing divides by zero. ``nonneg`` clamps the volume
at zero after every subset update (attenuation cannot be negative).

Subsets interleave the views in angle order (subset ``s`` holds every ``subsets``-th view), so
each one spans the whole arc; ``order="random"`` visits them in a new seeded random order each
iteration, ``"ordered"`` in sequence. One iteration is one pass over all subsets.
"""
from __future__ import annotations

import contextlib

import numpy as np

from clgs.errors import InputError
from clgs.geometry import Geometry
from clgs.io.validate import check_projections

_COLUMN_SUM_BUDGET = 1 << 30  # bytes of cached A_S^T 1 volumes; beyond it they are recomputed


def subsets_of(geometry: Geometry, subsets: int) -> list:
    """View indices of each ordered subset: every ``subsets``-th view in angle order."""
    n = geometry.n_views
    if not 1 <= int(subsets) <= n:
        raise InputError(f"subsets must lie between 1 and the number of views ({n}), got {subsets}")
    by_angle = np.argsort(np.mod(geometry.angles, 2 * np.pi), kind="stable")
    return [np.sort(by_angle[s::int(subsets)]) for s in range(int(subsets))]


def sart(projections, geometry: Geometry, n_iter: int = 10, subsets: int = 1, relaxation: float = 1.0,
         nonneg: bool = True, x0=None, callback=None, order: str = "random", seed: int = 0,
         verbose: bool = False, projector=None) -> np.ndarray:
    """SART (``subsets=1``) or OS-SART reconstruction: (Z, Y, X) float32 volume, values per mm.

    ``projections``: (n_views, V, U) line integrals. ``x0``: starting volume (default zeros).
    ``callback(iteration, volume)`` runs after each iteration (``iteration`` counts from 1;
    ``volume`` is a fresh (Z, Y, X) copy of the current estimate). ``verbose`` shows a tqdm bar.
    ``projector``: an existing :class:`CTProjector` for this geometry, to reuse its buffers.
    One function: the iteration loop keeps its ray and voxel normalisations and buffers in locals,
    so each update is a few array operations.
    """
    from clgs.ops.ct_projector import CTProjector

    b = check_projections(projections, geometry, neg_tolerance=None, source="sart")
    if int(n_iter) < 0:
        raise InputError(f"n_iter must be at least 0, got {n_iter}")
    if not np.isfinite(relaxation) or not 0 < relaxation < 2:
        raise InputError(f"relaxation must lie in (0, 2) for SART to converge, got {relaxation}")
    if order not in ("random", "ordered"):
        raise InputError(f"order must be 'random' or 'ordered', got {order!r}")
    b = b.astype(np.float32, copy=False)
    P = projector if projector is not None else CTProjector(geometry)
    if P.geometry is not geometry and P.geometry.to_dict() != geometry.to_dict():
        raise InputError("the projector was built for another geometry")
    shape = tuple(geometry.nVoxel)
    if x0 is None:
        x = np.zeros(shape, np.float32)
    else:
        x = np.array(x0, dtype=np.float32, copy=True)
        if x.shape != shape:
            raise InputError(f"x0 has shape {x.shape}, the geometry expects {shape}")
        if not np.all(np.isfinite(x)):
            raise InputError("x0 contains NaN or Inf values")
        if nonneg:
            np.maximum(x, 0, out=x)

    groups = subsets_of(geometry, subsets)
    nz, ny, nx = shape
    nv, nu = geometry.nDetector
    from clgs.progress import phase

    # the weights cost a forward and a backprojection (and the first call builds the kernels);
    # everything stays in the kernels' layouts (see CTProjector.pad_volume): no transposes per update
    with phase(f"SART's ray and voxel weights ({len(groups)} subset{'s' if len(groups) > 1 else ''})") if verbose \
            else contextlib.nullcontext():
        x_pad = P.pad_volume(x)
        x_int = x_pad[1:nx + 1, 1:ny + 1, 1:nz + 1]          # (X, Y, Z) view of the interior
        b_t = np.zeros((b.shape[0], nu, (nv + 7) // 8 * 8), np.float32)
        b_t[:, :, :nv] = b.transpose(0, 2, 1)
        rows = P.forward_padded(P.pad_volume(np.ones(shape, np.float32)))
        inv_rows = np.zeros_like(rows)
        ok = rows > 1e-6 * float(rows.max())
        inv_rows[ok] = 1.0 / rows[ok]                          # padded rows stay 0

        def inv_columns(views):
            ones = np.zeros((len(views), nu, b_t.shape[2]), np.float32)
            ones[:, :, :nv] = 1.0
            col = P.backward_internal(ones, views=views)[:, :, :nz]
            inv = np.zeros_like(col)
            good = col > 1e-6 * float(col.max()) if col.max() > 0 else col > 0
            inv[good] = 1.0 / col[good]
            return inv

        keep = len(groups) * x.nbytes <= _COLUMN_SUM_BUDGET
        cols = [inv_columns(v) for v in groups] if keep else None
    rng = np.random.default_rng(seed)
    lam = np.float32(relaxation)

    bar = None
    if verbose:
        from clgs.progress import progress_bar

        bar = progress_bar(total=int(n_iter), desc="SART" if len(groups) == 1 else f"OS-SART ({len(groups)} subsets)")
    try:
        for it in range(int(n_iter)):
            seq = rng.permutation(len(groups)) if order == "random" else range(len(groups))
            for s in seq:
                views = groups[s]
                resid = b_t[views] - P.forward_padded(x_pad, views=views)
                resid *= inv_rows[views]
                upd = P.backward_internal(resid, views=views)[:, :, :nz]
                upd *= cols[s] if keep else inv_columns(views)
                upd *= lam
                x_int += upd
                if nonneg:
                    np.maximum(x_int, 0, out=x_int)
            if bar is not None:
                bar.update(1)
            if callback is not None:
                callback(it + 1, np.ascontiguousarray(x_int.transpose(2, 1, 0)))
    finally:
        if bar is not None:
            bar.close()
    return np.ascontiguousarray(x_int.transpose(2, 1, 0))
