"""Analytic test phantoms: sums of uniform ellipsoids, with exact line integrals and voxelised
versions.

An ellipsoid of density ``mu`` (per mm) adds ``mu * chord length`` to every ray that crosses it,
so projections of these phantoms are exact and test the voxel projector and the reconstructions
without a reference implementation. Densities add where ellipsoids overlap (as in the
Shepp-Logan family), so holes are negative ellipsoids inside positive ones.

All lengths are world millimetres, points (x, y, z), as in :mod:`clgs.geometry`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clgs.errors import InputError
from clgs.geometry import Geometry


def _rotation(angles_zyz):
    """Rotation matrix from three Euler angles (radians) about z, then y, then z."""
    a, b, c = angles_zyz
    def rz(t):
        return np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1.0]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1.0, 0], [-np.sin(b), 0, np.cos(b)]])
    return rz(a) @ ry @ rz(c)


@dataclass(frozen=True)
class Ellipsoid:
    """A uniform ellipsoid: ``centre`` (x, y, z) mm, semi-axes ``axes`` (mm) along the rotated
    x, y, z axes, ``angles`` Euler z-y-z (radians), additive ``density`` (per mm)."""

    centre: tuple
    axes: tuple
    density: float
    angles: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        if np.any(np.asarray(self.axes, float) <= 0):
            raise InputError(f"ellipsoid semi-axes must be positive, got {self.axes}")

    @property
    def metric(self) -> np.ndarray:
        """M with (x - c)^T M (x - c) <= 1 inside."""
        r = _rotation(self.angles)
        return r @ np.diag(1.0 / np.asarray(self.axes, float) ** 2) @ r.T


def ball(centre=(0.0, 0.0, 0.0), radius=10.0, density=0.02) -> Ellipsoid:
    return Ellipsoid(tuple(centre), (radius,) * 3, float(density))


def chord_lengths(ellipsoids, origins, directions, half_line: bool) -> np.ndarray:
    """Sum over ellipsoids of density x the length of each ray inside it.

    ``origins`` and unit ``directions`` are (..., 3); ``half_line`` keeps only t > 0 (cone rays
    start at the source), otherwise the whole line counts.
    """
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    total = np.zeros(o.shape[:-1])
    for e in ellipsoids:
        m = e.metric
        oc = o - np.asarray(e.centre, float)
        md = d @ m
        a = np.einsum("...i,...i", md, d)
        b = np.einsum("...i,...i", md, oc)
        c = np.einsum("...i,...i", oc @ m, oc) - 1.0
        disc = b * b - a * c
        hit = disc > 0
        root = np.sqrt(np.where(hit, disc, 0.0))
        t1 = (-b - root) / a
        t2 = (-b + root) / a
        if half_line:
            t1 = np.maximum(t1, 0.0)
        length = np.where(hit, np.maximum(t2 - t1, 0.0), 0.0)
        total += e.density * length
    return total


def project(ellipsoids, geometry: Geometry) -> np.ndarray:
    """Exact line integrals (n_views, V, U), float64, of the phantom in ``geometry``."""
    out = np.empty(geometry.projection_shape)
    for v in range(geometry.n_views):
        o, d = geometry.rays(v, scene=False)
        out[v] = chord_lengths(ellipsoids, o, d, half_line=geometry.mode == "cone")
    return out


def voxelize(ellipsoids, geometry: Geometry, supersample: int = 3) -> np.ndarray:
    """(Z, Y, X) float32 volume: each voxel holds the mean density over ``supersample^3`` points."""
    s = int(supersample)
    if s < 1:
        raise InputError("supersample must be at least 1")
    grid = geometry.volume_grid(scene=False)
    nz, ny, nx = grid.shape
    sp = np.asarray(grid.spacing)
    offs = (np.arange(s) + 0.5) / s - 0.5
    vol = np.zeros((nz, ny, nx))
    axes = [grid.origin[a] + sp[a] * np.arange(grid.shape[2 - a]) for a in range(3)]
    for e in ellipsoids:
        m = e.metric
        c = np.asarray(e.centre, float)
        half = np.sqrt(np.diag(np.linalg.inv(m)))  # bounding box half sizes
        lo = [np.searchsorted(axes[a], c[a] - half[a] - sp[a]) for a in range(3)]
        hi = [np.searchsorted(axes[a], c[a] + half[a] + sp[a]) for a in range(3)]
        if any(h <= l for l, h in zip(lo, hi)):
            continue
        xs = (axes[0][lo[0]:hi[0], None] + offs[None] * sp[0]).ravel()
        ys = (axes[1][lo[1]:hi[1], None] + offs[None] * sp[1]).ravel()
        acc = np.zeros((hi[2] - lo[2], hi[1] - lo[1], hi[0] - lo[0]))
        for k in range(lo[2], hi[2]):
            for dz in offs:
                z = axes[2][k] + dz * sp[2]
                X, Y = np.meshgrid(xs - c[0], ys - c[1], indexing="xy")
                Z = z - c[2]
                q = (m[0, 0] * X * X + m[1, 1] * Y * Y + m[2, 2] * Z * Z
                     + 2 * (m[0, 1] * X * Y + m[0, 2] * X * Z + m[1, 2] * Y * Z))
                inside = (q <= 1.0).astype(np.float64)
                acc[k - lo[2]] += inside.reshape(hi[1] - lo[1], s, hi[0] - lo[0], s).sum((1, 3))
        vol[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]] += e.density * acc / s**3
    return vol.astype(np.float32)


def head_phantom(geometry: Geometry) -> list:
    """A head-like set of ellipsoids filling the volume: a dense shell (bone, 0.04/mm on top of
    tissue), soft tissue (0.02/mm), two tilted low-density cavities and small features of 2-30%
    contrast, scaled to the smallest half-extent of the volume and centred on it."""
    half = 0.5 * float(np.min(geometry.sVoxel[1:]))
    hz = 0.5 * float(geometry.sVoxel[0])
    zc = geometry.offOrigin[0]
    o = np.asarray(geometry.offOrigin[::-1], float)

    def at(x, y, z):
        return (o[0] + x * half, o[1] + y * half, zc + z * hz)

    def ax(a, b, c):
        return (a * half, b * half, c * hz)

    return [
        Ellipsoid(at(0, 0, 0), ax(0.70, 0.88, 0.80), 0.060),
        Ellipsoid(at(0, -0.01, 0), ax(0.64, 0.82, 0.74), -0.040),
        Ellipsoid(at(0.20, 0.05, 0.05), ax(0.10, 0.28, 0.25), -0.008, (np.deg2rad(-18), 0, 0)),
        Ellipsoid(at(-0.20, 0.05, 0.05), ax(0.13, 0.35, 0.28), -0.008, (np.deg2rad(18), 0, 0)),
        Ellipsoid(at(0, 0.35, 0.1), ax(0.18, 0.20, 0.18), 0.004),
        Ellipsoid(at(0, -0.45, -0.2), ax(0.05, 0.05, 0.05), 0.006),
        Ellipsoid(at(0.1, -0.45, -0.2), ax(0.04, 0.04, 0.04), 0.006),
        Ellipsoid(at(-0.15, -0.55, 0.3), ax(0.08, 0.04, 0.06), 0.005, (np.deg2rad(30), np.deg2rad(20), 0)),
        Ellipsoid(at(0.3, -0.2, -0.4), ax(0.06, 0.09, 0.12), 0.010, (0, np.deg2rad(35), 0)),
        Ellipsoid(at(-0.3, -0.1, -0.35), ax(0.05, 0.05, 0.20), -0.006),
    ]
