"""Rolled and pitched detectors for the voxel projector pair, through an upright stand-in.

The voxel projector (``cl/ct_projector.cl``) steps each detector column's rays along one in-plane
path, so it needs detector rows that are horizontal and columns along z. A detector turned out of
that (roll about its normal, pitch about its rows) is handled here: per view, an upright virtual
detector (columns along z, rows horizontal, facing the source's in-plane direction; cone beam:
at the real detector centre's depth) finer than the real one (``oversample``) catches the same
rays. Every real pixel's ray meets the virtual plane at one point; its line integral is the
bilinear interpolation of the four virtual pixels around that point (``R``, a sparse matrix a
view). Forward: ``R A_virtual``; transpose: ``A_virtual^T R^T``, so the pair stays an exact
transpose. The forward is exact up to that interpolation, which shrinks about as 1 / ``oversample``:
against a plain Joseph projector of the real rays, a smooth blob (sigma 2-3 voxels, pixels the
size of a voxel) is off by 6, 1.7, 0.9 and 0.35 % of its peak at 1, 2, 4 and 8 in cone beam
(``tests/test_vector_geometry.py``); 4 is the default, 16 times the real detector's rays.
"""
from __future__ import annotations

import math

import numpy as np

from clgs.errors import InputError
from clgs.geometry import Geometry

OVERSAMPLE = 4.0  # virtual pixels per real pixel step (the smaller of u and v)


def tilted_views(geometry: Geometry, tol: float = 1e-9) -> np.ndarray:
    """(n_views,) bool: views the voxel projector cannot take directly (u step with a z part, or
    v step off the z axis; parallel beam: a ray with a z part)."""
    vv = geometry.view_vectors(scene=False)
    us, vs = vv[:, 6:9], vv[:, 9:12]
    bad = (np.abs(us[:, 2]) > tol * np.linalg.norm(us, axis=1)) | \
        (np.hypot(vs[:, 0], vs[:, 1]) > tol * np.linalg.norm(vs, axis=1))
    if geometry.mode != "cone":
        bad |= np.abs(vv[:, 2]) > tol * np.linalg.norm(vv[:, 0:3], axis=1)
    return bad


def upright_stand_in(geometry: Geometry, nvp: int, oversample: float | None = None):
    """(virtual Geometry, [R per view]): R maps the virtual view's projections in the kernels'
    layout (U', Vp' rounded up to 8, v fastest) to the real view's (U, ``nvp``), as a
    scipy.sparse CSR matrix of bilinear weights."""
    from scipy import sparse

    g = geometry
    vv = g.view_vectors(scene=False)
    nv, nu = g.nDetector
    iu = np.arange(nu) - (nu - 1) / 2.0
    iv = np.arange(nv) - (nv - 1) / 2.0
    cone = g.mode == "cone"
    steps = np.minimum(np.linalg.norm(vv[:, 6:9], axis=1), np.linalg.norm(vv[:, 9:12], axis=1))
    delta = float(steps.min()) / float(OVERSAMPLE if oversample is None else oversample)
    frames = []
    for i, row in enumerate(vv):
        first, det, u, v = row[0:3], row[3:6], row[6:9], row[9:12]
        pix = det + iu[None, :, None] * u + iv[:, None, None] * v  # (V, U, 3)
        if cone:
            c = det - first
            n = np.array([c[0], c[1], 0.0])
            if np.linalg.norm(n) < 1e-9 * np.linalg.norm(c):
                raise InputError(f"view {i}: the detector centre lies straight above or below the source; the "
                                 "voxel projector needs a beam that crosses the volume sideways")
            n /= np.linalg.norm(n)
            depth = float(c @ n)
            r = pix - first
            rn = r @ n
            if np.any(rn <= 1e-3 * depth):
                raise InputError(f"view {i}: some detector rays run parallel to the rotation plane's normal or "
                                 "backwards; the voxel projector cannot take this detector")
            hit = first + (depth / rn)[..., None] * r
            origin = first + depth * n
        else:
            if abs(first[2]) > 1e-9:
                raise InputError(f"view {i}: parallel rays with a vertical part; the voxel projector needs "
                                 "horizontal rays (the Gaussian methods take any)")
            n = -first / np.linalg.norm(first)
            hit = pix
            origin = det
        eu = np.array([-n[1], n[0], 0.0])
        a = (hit - origin) @ eu
        b = hit[..., 2] - origin[2]
        frames.append((first, origin, eu, a, b))
    span_a = max(float(f[3].max() - f[3].min()) for f in frames)
    span_b = max(float(f[4].max() - f[4].min()) for f in frames)
    nu2 = int(math.ceil(span_a / delta)) + 4
    nv2 = int(math.ceil(span_b / delta)) + 4
    nvp2 = (nv2 + 7) // 8 * 8
    ez = np.array([0.0, 0.0, 1.0])
    vectors, mats = [], []
    rows_idx = (np.arange(nu)[None, :] * nvp + np.arange(nv)[:, None]).ravel()  # (V, U) -> U * nvp + V
    for first, origin, eu, a, b in frames:
        a_mid, b_mid = 0.5 * (a.max() + a.min()), 0.5 * (b.max() + b.min())
        vectors.append([*first, *(origin + a_mid * eu + b_mid * ez), *(delta * eu), *(delta * ez)])
        fu = (a - a_mid) / delta + (nu2 - 1) / 2.0
        fv = (b - b_mid) / delta + (nv2 - 1) / 2.0
        i0, j0 = np.floor(fu).astype(np.int64), np.floor(fv).astype(np.int64)
        wu, wv = fu - i0, fv - j0
        rr, cc, ww = [], [], []
        for di, w_u in ((0, 1 - wu), (1, wu)):
            for dj, w_v in ((0, 1 - wv), (1, wv)):
                rr.append(rows_idx)
                cc.append(((i0 + di) * nvp2 + (j0 + dj)).ravel())
                ww.append((w_u * w_v).ravel())
        mats.append(sparse.csr_matrix((np.concatenate(ww), (np.concatenate(rr), np.concatenate(cc))),
                                      shape=(nu * nvp, nu2 * nvp2)))
    # in world mm, as the vectors above (the voxel projector works there): the volume's centre is
    # its offOrigin and the isocentre the world's origin
    virtual = Geometry.from_vectors(vectors, (nv2, nu2), g.nVoxel, g.dVoxel, tuple(g.centre_xyz[::-1]), g.mode)
    return virtual, mats
