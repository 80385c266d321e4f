"""Shape-guided initialisation: Gaussians laid out on an anatomy's template.

Reference centres are drawn from the template's interior with a weight that grows near the
surface (``1 + boundary_weight * exp(-(d / band)^2)``, ``d`` the signed distance), so the bone's
outline gets more and smaller Gaussians than its core. Each centre gets

* an isotropic scale from the mean distance to its 3 nearest neighbours (scipy's KD-tree);
* near the surface (``|d| < band``), its scale along the template normal thinned by ``tau`` and a
  rotation whose third axis is that normal, so a flat Gaussian lies along the cortex;
* a density ``atlas_mean(p) / max(n(p), 1)``, with ``n`` the field of all these Gaussians at unit
  density evaluated at the centres (the point voxelizer): overlapping Gaussians share the
  atlas value instead of adding up to a multiple of it.

With a density atlas the bone's surroundings (soft tissue) can be laid out too
(:func:`initialise_surroundings`): centres drawn uniformly where the atlas mean is above a fraction
of its maximum outside the template's bone, the same nearest-neighbour scales, and densities
``atlas_mean(p) / max(n(p), 1)`` with ``n`` counting the bone's Gaussians as well, so the two
sets together reproduce the atlas across the bone's surface. The shape-guided method starts its
free Gaussians there instead of on a sparse-view FDK, whose streaks they would otherwise have to
unlearn (at 5 views the atlas is ~25 dB from a subject's CT, the FDK ~18 dB).

Everything here works in mm in the template's frame; callers map to the scene.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clgs.errors import InputError


@dataclass
class ShapeInit:
    """Initial shape-guided Gaussians in mm: reference centres, scales, quaternions, densities."""

    centres: np.ndarray  # (N, 3) mm
    scales: np.ndarray  # (N, 3) mm
    quats: np.ndarray  # (N, 4) (w, x, y, z)
    densities: np.ndarray  # (N,) atlas units
    overlap: np.ndarray  # (N,) n(p) at the centres
    near_surface: np.ndarray  # (N,) bool


def sample_reference_centres(template, n: int, *, boundary_weight: float = 4.0, band_mm: float | None = None,
                             seed: int = 0) -> np.ndarray:
    """``n`` points (mm) inside the template, denser near its surface; seeded.

    Voxels with signed distance <= half a voxel are candidates; each is drawn with probability
    proportional to the boundary weight (with replacement when ``n`` exceeds the candidates) and
    the point is jittered uniformly within its voxel."""
    if n < 1:
        raise InputError(f"need at least one shape-guided Gaussian, got {n}")
    spacing = np.asarray(template.spacing, float)  # (dz, dy, dx)
    band = float(band_mm if band_mm is not None else 2.0 * spacing.max())
    sdf = template.sdf
    cand = np.flatnonzero(sdf.reshape(-1) <= 0.5 * spacing.min())
    if cand.size == 0:
        raise InputError("the template has no interior voxels: its signed distance is positive everywhere")
    d = sdf.reshape(-1)[cand].astype(np.float64)
    w = 1.0 + boundary_weight * np.exp(-((d / band) ** 2))
    rng = np.random.default_rng(seed)
    pick = rng.choice(cand.size, size=n, replace=n > cand.size, p=w / w.sum())
    k, j, i = np.unravel_index(cand[pick], sdf.shape)
    idx = np.stack([i, j, k], 1).astype(np.float64) + rng.uniform(-0.5, 0.5, (n, 3))
    origin_xyz = np.asarray(template.origin[::-1], float)
    return origin_xyz + idx * spacing[::-1]


def quaternion_from_z_to(normals: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of the shortest rotations taking e_z onto each unit normal.

    A normal opposite to e_z (where that rotation's axis is undefined) gets a half turn about x."""
    n = np.asarray(normals, float)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], 1)
    flip = q[:, 0] < 1e-6
    q[flip] = (0.0, 1.0, 0.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def nearest_neighbour_spacing(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance from each point to its ``k`` nearest neighbours."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return np.ones(len(points))
    kk = min(k, len(points) - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)
    return np.maximum(dist[:, 1:].mean(1), 1e-6)


def overlap_count(centres_mm, scales_mm, quats, to_scene, backend: str = "cl") -> np.ndarray:
    """n(p): the field of all Gaussians at unit density, evaluated at their own centres."""
    return overlap_count_at(centres_mm, scales_mm, quats, centres_mm, to_scene, backend=backend)


class SceneMap:
    """mm -> scene units of one scan (a callable with its ``scale``), for the kernels."""

    def __init__(self, geometry):
        self.geometry = geometry
        self.scale = geometry.scale

    def __call__(self, points_mm):
        return self.geometry.world_to_scene(points_mm)


def initialise(template, atlas, geometry, n: int, *, tau: float = 0.5, boundary_weight: float = 4.0,
               band_mm: float | None = None, seed: int = 0, backend: str = "cl") -> ShapeInit:
    """The shape-guided Gaussians of ``template`` for a scan with ``geometry`` (see module doc).

    ``atlas`` may be None: every centre then starts at 0.05 (1/mm, about cancellous bone) before
    the overlap division."""
    if not 0 < tau <= 1:
        raise InputError(f"tau (thinning along the normal) must be in (0, 1], got {tau}")
    centres = sample_reference_centres(template, n, boundary_weight=boundary_weight, band_mm=band_mm, seed=seed)
    s = nearest_neighbour_spacing(centres)
    scales = np.repeat(s[:, None], 3, 1)
    quats = np.zeros((n, 4)); quats[:, 0] = 1.0
    band = float(band_mm if band_mm is not None else 2.0 * max(template.spacing))
    d = template.sdf_at(centres)
    near = np.abs(d) < band
    if near.any():
        normals = template.normal_at(centres[near])
        quats[near] = quaternion_from_z_to(normals)
        scales[near, 2] *= tau
    to_scene = SceneMap(geometry)
    overlap = overlap_count(centres, scales, quats, to_scene, backend=backend)
    base = np.asarray(atlas.mean_at(centres), np.float64) if atlas is not None else np.full(n, 0.05)
    dens = np.maximum(base, 0.0) / np.maximum(overlap, 1.0)
    return ShapeInit(centres, scales, quats, dens, overlap, near)


def sample_surrounding_centres(template, atlas, n: int, *, threshold: float = 0.05, seed: int = 0) -> np.ndarray:
    """``n`` points (mm) outside the template's bone where the atlas mean exceeds ``threshold`` x
    its maximum (the tissue around the bone), uniformly over those atlas voxels, jittered within
    the voxel; seeded. Fewer when there are fewer voxels (drawn without replacement); none when
    the atlas holds the bone alone."""
    if n < 1:
        raise InputError(f"need at least one surrounding Gaussian, got {n}")
    grid = atlas.grid()
    pts = grid.points().reshape(-1, 3)
    mean = atlas.mean.reshape(-1)
    peak = float(mean.max())
    if not peak > 0:
        raise InputError("the density atlas is zero everywhere: nothing to lay the surroundings out from")
    spacing = np.asarray(atlas.spacing, float)  # (dz, dy, dx)
    outside = template.sdf_at(pts) > 0.5 * float(min(template.spacing))
    cand = np.flatnonzero(outside & (mean > threshold * peak))
    if cand.size == 0:  # an atlas of the bone alone
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(cand.size, size=min(n, cand.size), replace=False))
    jitter = rng.uniform(-0.5, 0.5, (pick.size, 3)) * spacing[::-1]
    return pts[cand[pick]] + jitter


def initialise_surroundings(inside: ShapeInit, template, atlas, geometry, n: int, *, threshold: float = 0.05,
                            seed: int = 0, backend: str = "cl") -> ShapeInit | None:
    """Gaussians for the tissue around the bone (module doc), given the bone's own ``inside``.

    Isotropic scales from the nearest-neighbour spacing among themselves; densities
    ``atlas_mean / max(n, 1)`` where ``n`` is the field at unit density of these Gaussians and of
    ``inside``'s, so the two sets share the atlas value where they meet. None when the atlas has
    no tissue around the bone."""
    centres = sample_surrounding_centres(template, atlas, n, threshold=threshold, seed=seed)
    m = len(centres)
    if m == 0:
        return None
    s = nearest_neighbour_spacing(centres)
    scales = np.repeat(s[:, None], 3, 1)
    quats = np.zeros((m, 4)); quats[:, 0] = 1.0
    to_scene = SceneMap(geometry)
    all_c = np.concatenate([centres, inside.centres])
    all_s = np.concatenate([scales, inside.scales])
    all_q = np.concatenate([quats, inside.quats])
    overlap = overlap_count_at(all_c, all_s, all_q, centres, to_scene, backend=backend)
    base = np.maximum(np.asarray(atlas.mean_at(centres), np.float64), 0.0)
    dens = base / np.maximum(overlap, 1.0)
    return ShapeInit(centres, scales, quats, dens, overlap, np.zeros(m, bool))


def overlap_count_at(centres_mm, scales_mm, quats, points_mm, to_scene, backend: str = "cl") -> np.ndarray:
    """The field of the Gaussians at unit density, evaluated at ``points_mm``."""
    import torch

    means = torch.as_tensor(to_scene(centres_mm), dtype=torch.float32)
    scales = torch.as_tensor(scales_mm * to_scene.scale, dtype=torch.float32)
    q = torch.as_tensor(quats, dtype=torch.float32)
    pts = torch.as_tensor(to_scene(points_mm), dtype=torch.float32)
    ones = torch.ones(len(means), dtype=torch.float32)
    if backend == "cl":
        from clgs.ops.voxelizer import voxelize_points
    else:
        from clgs.reference.voxelization import voxelize_points
    with torch.no_grad():
        return voxelize_points(means, scales, q, ones, pts).numpy().astype(np.float64)
