"""Anatomy templates and population subjects on regular grids in mm.

Conventions (shared with :mod:`clgs.shape_model`):

* A grid is ``shape`` (Z, Y, X), ``spacing`` (dz, dy, dx) in mm and ``origin`` (z, y, x) in mm,
  the position of the centre of voxel [0, 0, 0] (TIGRE-style ordering, like ``dVoxel``).
  :meth:`Template.grid` converts to :class:`clgs.geometry.Grid`, which stores (x, y, z).
* Points, mesh vertices and normals are (x, y, z) in mm, as everywhere else in clgs.
* Signed distances are in mm, negative inside the bone.

Only NumPy/SciPy at import time; torch is not needed here.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

TEMPLATE_FORMAT = "clgs.template"
TEMPLATE_VERSION = 1


# --------------------------------------------------------------------------------------- grids
def _triple(name, value, dtype=float):
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers (Z, Y, X), got {value!r}")
    return tuple(dtype(v) for v in arr)


def grid_points(shape, spacing, origin) -> np.ndarray:
    """All voxel centres of a grid as an array (Z, Y, X, 3) of (x, y, z) in mm."""
    shape, spacing, origin = _triple("shape", shape, int), _triple("spacing", spacing), _triple("origin", origin)
    axes = [origin[a] + spacing[a] * np.arange(shape[a]) for a in range(3)]  # z, y, x axes
    z, y, x = np.meshgrid(*axes, indexing="ij")
    return np.stack([x, y, z], -1)


def box_grid(lo_xyz, hi_xyz, max_cells: int = None, spacing: float = None):
    """A grid (shape, spacing, origin) covering the box [lo, hi] (x, y, z mm) with isotropic cells.

    Either ``max_cells`` (cells along the longest side) or ``spacing`` (mm) sets the resolution."""
    lo, hi = np.asarray(lo_xyz, float), np.asarray(hi_xyz, float)
    size = hi - lo
    if np.any(size <= 0):
        raise ValueError(f"empty box: lo={lo}, hi={hi}")
    if spacing is None:
        if not max_cells or max_cells < 2:
            raise ValueError("give max_cells >= 2 or a spacing in mm")
        spacing = float(size.max()) / (max_cells - 1)
    n = np.maximum(np.ceil(size / spacing).astype(int) + 1, 2)
    centre = 0.5 * (lo + hi)
    origin_xyz = centre - 0.5 * (n - 1) * spacing
    return (tuple(int(v) for v in n[::-1]), (float(spacing),) * 3, tuple(float(v) for v in origin_xyz[::-1]))


def sample_volume(volume, spacing, origin, points, fill: Optional[float] = 0.0, order: int = 1) -> np.ndarray:
    """Trilinear (order 1) samples of a (Z, Y, X) volume at points (..., 3) (x, y, z mm);
    ``fill`` outside the grid, or the nearest border value when ``fill`` is None."""
    from scipy.ndimage import map_coordinates

    spacing, origin = np.asarray(spacing, float), np.asarray(origin, float)
    pts = np.asarray(points, float)
    idx = (pts[..., ::-1] - origin) / spacing  # (..., 3) as (k, j, i)
    coords = np.moveaxis(idx.reshape(-1, 3), -1, 0)
    if fill is None:
        out = map_coordinates(np.asarray(volume, np.float32), coords, order=order, mode="nearest")
    else:
        out = map_coordinates(np.asarray(volume, np.float32), coords, order=order, mode="constant", cval=fill)
    return out.reshape(pts.shape[:-1]).astype(np.float32)


# --------------------------------------------------------------------------------------- meshes
def _check_mesh(vertices, faces):
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise ValueError(f"mesh vertices must be (V>=4, 3) in mm, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise ValueError(f"mesh faces must be (F>=4, 3) vertex indices, got shape {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"mesh faces index vertices 0..{len(v) - 1}, found {f.min()}..{f.max()}")
    if not np.all(np.isfinite(v)):
        raise ValueError("mesh vertices contain NaN or Inf")
    return v, f


def mesh_to_label(vertices, faces, shape, spacing, origin) -> np.ndarray:
    """Inside/outside (bool, Z, Y, X) of a closed triangle mesh, by ray parity along +x.

    Each voxel column (fixed y, z) is intersected with every triangle whose y-z bounding box
    it crosses; a voxel is inside when an odd number of crossings lie before its centre. The
    columns are nudged by an irrational fraction of a cell so that meshes whose vertices sit on
    grid lines (e.g. from marching cubes) do not hit edges exactly."""
    v, f = _check_mesh(vertices, faces)
    shape, spacing, origin = _triple("shape", shape, int), _triple("spacing", spacing), _triple("origin", origin)
    Z, Y, X = shape
    dz, dy, dx = spacing
    oz, oy, ox = origin
    tri = v[f]  # (F, 3 corners, xyz)
    jf = (tri[..., 1] - oy) / dy - 1.37e-4 * np.sqrt(2.0)
    kf = (tri[..., 2] - oz) / dz - 2.11e-4 * np.sqrt(3.0)
    j0 = np.clip(np.ceil(jf.min(1)), 0, Y).astype(np.int64)
    j1 = np.clip(np.floor(jf.max(1)), -1, Y - 1).astype(np.int64)
    k0 = np.clip(np.ceil(kf.min(1)), 0, Z).astype(np.int64)
    k1 = np.clip(np.floor(kf.max(1)), -1, Z - 1).astype(np.int64)
    nj = np.maximum(j1 - j0 + 1, 0)
    nk = np.maximum(k1 - k0 + 1, 0)
    count = nj * nk
    toggles = np.zeros((Z, Y, X + 1), np.int32)
    if count.sum() == 0:
        return np.zeros(shape, bool)
    t = np.repeat(np.arange(len(f)), count)
    start = np.repeat(np.cumsum(count) - count, count)
    local = np.arange(t.size) - start
    j = j0[t] + local % nj[t]
    k = k0[t] + local // nj[t]
    # barycentric coordinates of the column point in the triangle's y-z projection
    py, pz = j.astype(np.float64), k.astype(np.float64)
    ay, az = jf[t, 0], kf[t, 0]
    by, bz = jf[t, 1], kf[t, 1]
    cy, cz = jf[t, 2], kf[t, 2]
    w0 = (by - py) * (cz - pz) - (bz - pz) * (cy - py)
    w1 = (cy - py) * (az - pz) - (cz - pz) * (ay - py)
    w2 = (ay - py) * (bz - pz) - (az - pz) * (by - py)
    area = w0 + w1 + w2
    hit = (np.abs(area) > 1e-12) & (((w0 >= 0) & (w1 >= 0) & (w2 >= 0)) | ((w0 <= 0) & (w1 <= 0) & (w2 <= 0)))
    t, j, k = t[hit], j[hit], k[hit]
    w0, w1, w2, area = w0[hit] / area[hit], w1[hit] / area[hit], w2[hit] / area[hit], area[hit]
    xs = w0 * tri[t, 0, 0] + w1 * tri[t, 1, 0] + w2 * tri[t, 2, 0]
    ic = np.clip(np.ceil((xs - ox) / dx), 0, X).astype(np.int64)
    np.add.at(toggles, (k, j, ic), 1)
    return (np.cumsum(toggles, axis=2)[..., :X] % 2) == 1


def sample_surface(vertices, faces, step: float, seed: int = 0, return_faces: bool = False):
    """Points (N, 3) on the mesh surface, about one per ``step``^2 mm^2, plus every face centroid
    (and, with ``return_faces``, the face each point lies on)."""
    v, f = _check_mesh(vertices, faces)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = np.ceil(area / (step * step)).astype(np.int64)
    rng = np.random.default_rng(seed)
    t = np.repeat(np.arange(len(f)), n)
    r1, r2 = rng.random(t.size), rng.random(t.size)
    s = np.sqrt(r1)
    a, b, c = 1 - s, s * (1 - r2), s * r2
    pts = a[:, None] * tri[t, 0] + b[:, None] * tri[t, 1] + c[:, None] * tri[t, 2]
    pts = np.concatenate([tri.mean(1), pts], 0)
    ids = np.concatenate([np.arange(len(f)), t])
    return (pts, ids) if return_faces else pts


def point_triangle_distance(p, a, b, c) -> np.ndarray:
    """Exact distance from points p (N, 3) to triangles (a, b, c) (N, 3 each), by the closest-point
    regions (vertex, edge, face) of the triangle."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    safe = np.where(np.abs(denom) > 1e-300, denom, 1.0)
    v_, w_ = vb / safe, vc / safe
    q = a + v_[:, None] * ab + w_[:, None] * ac  # inside the face
    eps = 1e-300

    def on_edge(mask, start, direction, t):
        q[mask] = start[mask] + np.clip(t[mask], 0, 1)[:, None] * direction[mask]

    bc = c - b
    on_edge((vc <= 0) & (d1 >= 0) & (d3 <= 0), a, ab, d1 / np.where(np.abs(d1 - d3) > eps, d1 - d3, 1.0))
    on_edge((vb <= 0) & (d2 >= 0) & (d6 <= 0), a, ac, d2 / np.where(np.abs(d2 - d6) > eps, d2 - d6, 1.0))
    e = (d4 - d3) + (d5 - d6)
    on_edge((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b, bc, (d4 - d3) / np.where(np.abs(e) > eps, e, 1.0))
    m = (d1 <= 0) & (d2 <= 0)
    q[m] = a[m]
    m = (d3 >= 0) & (d4 <= d3)
    q[m] = b[m]
    m = (d6 >= 0) & (d5 <= d6)
    q[m] = c[m]
    return np.linalg.norm(p - q, axis=1)


def mesh_distance(points, vertices, faces, k: int = 8, step: float = None) -> np.ndarray:
    """Exact unsigned distance (mm) from points (N, 3) to a triangle mesh: candidate faces from the
    ``k`` nearest dense surface samples (KD-tree), then exact point-triangle distances."""
    from scipy.spatial import cKDTree

    v, f = _check_mesh(vertices, faces)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if step is None:
        edges = np.linalg.norm(v[f[:, 1]] - v[f[:, 0]], axis=1)
        step = float(np.median(edges))
    samples, ids = sample_surface(v, f, step, return_faces=True)
    _, nn = cKDTree(samples).query(pts, k=min(k, len(samples)))
    nn = nn.reshape(len(pts), -1)
    tri = f[ids[nn.reshape(-1)]]
    rep = np.repeat(pts, nn.shape[1], axis=0)
    d = point_triangle_distance(rep, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]])
    return d.reshape(len(pts), -1).min(1)


def mesh_to_sdf(vertices, faces, shape, spacing, origin, label=None, band_cells: float = 3.0) -> np.ndarray:
    """Signed distance (float32 mm, negative inside) of a closed mesh on a grid.

    Inside/outside from :func:`mesh_to_label`; the magnitude is the Euclidean distance
    transform far from the surface (about half a voxel off), and within ``band_cells`` of it
    the exact distance to the triangles (:func:`mesh_distance`)."""
    from scipy.ndimage import distance_transform_edt

    shape, spacing, origin = _triple("shape", shape, int), _triple("spacing", spacing), _triple("origin", origin)
    if label is None:
        label = mesh_to_label(vertices, faces, shape, spacing, origin)
    label = np.asarray(label, bool)
    h = min(spacing)
    if not label.any():
        raise ValueError("the mesh does not cover any voxel centre of the grid: is it inside the grid "
                         "and larger than a voxel?")
    d_out = distance_transform_edt(~label, sampling=spacing)
    d_in = distance_transform_edt(label, sampling=spacing)
    sdf = np.where(label, -(d_in - 0.5 * h), d_out - 0.5 * h)
    band = np.abs(sdf) < band_cells * h
    d = mesh_distance(grid_points(shape, spacing, origin)[band], vertices, faces)
    sdf[band] = np.where(label[band], -d, d)
    return sdf.astype(np.float32)


def vertex_normals(vertices, faces) -> np.ndarray:
    """Unit area-weighted vertex normals (V, 3), oriented outwards (positive enclosed volume)."""
    v, f = _check_mesh(vertices, faces)
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    signed_volume = np.einsum("ij,ij->", tri[:, 0], fn) / 6.0
    if signed_volume < 0:
        fn = -fn
    n = np.zeros_like(v)
    for c in range(3):
        np.add.at(n, f[:, c], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.maximum(norm, 1e-12)).astype(np.float32)


def mesh_from_sdf(sdf, spacing, origin, level: float = 0.0):
    """The ``level`` iso-surface of a signed distance volume: (vertices (x, y, z) mm, faces)."""
    from skimage.measure import marching_cubes

    sdf = np.asarray(sdf, np.float32)
    if not (sdf.min() < level < sdf.max()):
        raise ValueError(f"the volume has no {level} iso-surface (range {sdf.min()}..{sdf.max()})")
    verts, faces, _, _ = marching_cubes(sdf, level=level, spacing=tuple(float(s) for s in spacing))
    verts = verts + np.asarray(origin, float)  # (z, y, x) mm
    verts = verts[:, ::-1].copy()  # to (x, y, z)
    faces = faces.astype(np.int64)
    # marching cubes orients faces by gradient; make the normals point outwards
    tri = verts[faces]
    vol = np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    if vol < 0:
        faces = faces[:, ::-1].copy()
    return verts.astype(np.float64), faces


def _atomic_save_npz(path, arrays: dict):
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _json_array(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj, sort_keys=True).encode("utf-8"), dtype=np.uint8).copy()


def _json_from_array(arr) -> dict:
    return json.loads(bytes(np.asarray(arr, np.uint8)).decode("utf-8"))


# --------------------------------------------------------------------------------------- template
@dataclass
class Template:
    """The reference bone: label and signed distance on a grid, and its surface mesh.

    label: (Z, Y, X) bool, True inside. sdf: (Z, Y, X) float32 mm, negative inside.
    vertices (V, 3) (x, y, z) mm and faces (F, 3) int: the surface. normals: (V, 3) unit,
    outwards (computed from the mesh when not given). spacing, origin: (Z, Y, X) mm."""

    label: np.ndarray
    sdf: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    spacing: tuple
    origin: tuple
    normals: Optional[np.ndarray] = None
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.spacing = _triple("spacing", self.spacing)
        self.origin = _triple("origin", self.origin)
        if min(self.spacing) <= 0:
            raise ValueError(f"template spacing must be positive, got {self.spacing}")
        self.sdf = np.asarray(self.sdf, np.float32)
        self.label = np.asarray(self.label, bool)
        if self.sdf.ndim != 3 or self.label.shape != self.sdf.shape:
            raise ValueError(f"template label {self.label.shape} and sdf {self.sdf.shape} must be the "
                             "same (Z, Y, X) shape")
        if not np.all(np.isfinite(self.sdf)):
            raise ValueError("template signed distance contains NaN or Inf")
        self.vertices, self.faces = _check_mesh(self.vertices, self.faces)
        if self.normals is None:
            self.normals = vertex_normals(self.vertices, self.faces)
        self.normals = np.asarray(self.normals, np.float32)
        if self.normals.shape != self.vertices.shape:
            raise ValueError(f"normals {self.normals.shape} must match vertices {self.vertices.shape}")

    # ---- construction
    @classmethod
    def from_mesh(cls, vertices, faces, spacing: float = 2.0, margin: float = 10.0, name: str = "",
                  shape=None, origin=None, meta=None) -> "Template":
        """Voxelise a closed surface: a grid of isotropic ``spacing`` mm around it with ``margin`` mm
        on every side (or the given ``shape``/``origin``)."""
        v, f = _check_mesh(vertices, faces)
        if shape is None:
            shape, sp, origin = box_grid(v.min(0) - margin, v.max(0) + margin, spacing=float(spacing))
        else:
            sp = _triple("spacing", spacing if np.ndim(spacing) else (spacing,) * 3)
            if origin is None:
                raise ValueError("give origin together with shape")
        label = mesh_to_label(v, f, shape, sp, origin)
        sdf = mesh_to_sdf(v, f, shape, sp, origin, label=label)
        return cls(label, sdf, v, f, sp, origin, name=name, meta=dict(meta or {}))

    @classmethod
    def from_sdf(cls, sdf, spacing, origin, name: str = "", meta=None) -> "Template":
        """A template from a signed distance volume (mm, negative inside); surface by marching cubes."""
        verts, faces = mesh_from_sdf(sdf, spacing, origin)
        return cls(np.asarray(sdf) < 0, sdf, verts, faces, spacing, origin, name=name, meta=dict(meta or {}))

    # ---- geometry
    @property
    def shape(self) -> tuple:
        return tuple(int(s) for s in self.sdf.shape)

    @property
    def extent_mm(self) -> tuple:
        """Size (Z, Y, X) of the grid box in mm (centre to centre of the end voxels)."""
        return tuple((n - 1) * s for n, s in zip(self.shape, self.spacing))

    def bounds(self):
        """(lo, hi) corners (x, y, z) mm of the grid's voxel centres."""
        lo = np.asarray(self.origin[::-1])
        return lo, lo + np.asarray(self.extent_mm[::-1])

    def grid(self):
        """The grid as a :class:`clgs.geometry.Grid` (origin and spacing as x, y, z)."""
        from clgs.geometry import Grid

        return Grid(self.shape, tuple(self.origin[::-1]), tuple(self.spacing[::-1]))

    def points(self) -> np.ndarray:
        return grid_points(self.shape, self.spacing, self.origin)

    def model_grid(self, max_cells: int = 64):
        """(shape, spacing, origin) of a coarser isotropic grid over the same box, for velocities."""
        lo, hi = self.bounds()
        return box_grid(lo, hi, max_cells=max_cells)

    def sdf_at(self, points) -> np.ndarray:
        """Signed distance (mm) at points (..., 3); outside the grid the border value is extended
        by the distance to the grid box (a safe over-estimate far from the bone)."""
        pts = np.asarray(points, float)
        lo, hi = self.bounds()
        inside = np.clip(pts, lo, hi)
        d = sample_volume(self.sdf, self.spacing, self.origin, inside, order=1)
        return d + np.linalg.norm(pts - inside, axis=-1).astype(np.float32)

    def normal_at(self, points) -> np.ndarray:
        """Unit outward normals (..., 3) from the signed distance gradient (central differences)."""
        pts = np.asarray(points, float)
        h = 0.5 * min(self.spacing)
        g = np.stack([self.sdf_at(pts + h * e) - self.sdf_at(pts - h * e) for e in np.eye(3)], -1)
        n = np.linalg.norm(g, axis=-1, keepdims=True)
        return (g / np.maximum(n, 1e-12)).astype(np.float32)

    def content_hash(self) -> str:
        """A hash of the template's arrays (used to key cached models)."""
        h = hashlib.sha256()
        for a in (self.sdf, self.vertices.astype(np.float64), self.faces.astype(np.int64),
                  np.asarray(self.spacing), np.asarray(self.origin)):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:16]

    # ---- files
    def save(self, path) -> None:
        """One npz (format ``clgs.template``), written atomically."""
        meta = {"format": TEMPLATE_FORMAT, "version": TEMPLATE_VERSION, "name": self.name, "meta": self.meta}
        _atomic_save_npz(path, dict(
            label=self.label.astype(np.uint8), sdf=self.sdf, vertices=self.vertices, faces=self.faces,
            normals=self.normals, spacing=np.asarray(self.spacing), origin=np.asarray(self.origin),
            metadata=_json_array(meta)))

    @classmethod
    def load(cls, path) -> "Template":
        with np.load(path, allow_pickle=False) as z:
            if "metadata" not in z.files:
                raise ValueError(f"{path} is not a clgs template (no metadata)")
            meta = _json_from_array(z["metadata"])
            if meta.get("format") != TEMPLATE_FORMAT:
                raise ValueError(f"{path} is not a clgs template (format {meta.get('format')!r})")
            if meta.get("version", 0) > TEMPLATE_VERSION:
                raise ValueError(f"{path} is template format version {meta['version']}; this clgs reads "
                                 f"up to {TEMPLATE_VERSION}: upgrade clgs")
            return cls(z["label"].astype(bool), z["sdf"], z["vertices"], z["faces"], tuple(z["spacing"]),
                       tuple(z["origin"]), normals=z["normals"], name=meta.get("name", ""),
                       meta=meta.get("meta", {}))


# --------------------------------------------------------------------------------------- subjects
@dataclass
class Subject:
    """One member of a population (or a held-out case): its surface and optionally a CT volume.

    vertices (V, 3) (x, y, z) mm, faces (F, 3). volume: (Z, Y, X) float32 attenuation (per mm),
    on the grid given by spacing/origin (Z, Y, X mm); None when only the shape is known."""

    id: str
    vertices: np.ndarray
    faces: np.ndarray
    volume: Optional[np.ndarray] = None
    spacing: Optional[tuple] = None
    origin: Optional[tuple] = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.id = str(self.id)
        self.vertices, self.faces = _check_mesh(self.vertices, self.faces)
        if self.volume is not None:
            self.volume = np.asarray(self.volume, np.float32)
            if self.volume.ndim != 3:
                raise ValueError(f"subject {self.id}: volume must be (Z, Y, X), got {self.volume.shape}")
            if self.spacing is None or self.origin is None:
                raise ValueError(f"subject {self.id}: a volume needs its spacing and origin (Z, Y, X mm)")
            self.spacing = _triple("spacing", self.spacing)
            self.origin = _triple("origin", self.origin)

    def label_on(self, shape, spacing, origin) -> np.ndarray:
        return mesh_to_label(self.vertices, self.faces, shape, spacing, origin)

    def sdf_on(self, shape, spacing, origin) -> np.ndarray:
        """Signed distance (mm) of the subject's surface on a grid."""
        return mesh_to_sdf(self.vertices, self.faces, shape, spacing, origin)

    def volume_at(self, points) -> np.ndarray:
        """CT values at points (..., 3) (x, y, z mm), trilinear, 0 (air) outside the volume."""
        if self.volume is None:
            raise ValueError(f"subject {self.id} has no CT volume")
        return sample_volume(self.volume, self.spacing, self.origin, points, fill=0.0)

    def volume_on(self, shape, spacing, origin) -> np.ndarray:
        return self.volume_at(grid_points(shape, spacing, origin))

    def content_hash(self) -> str:
        h = hashlib.sha256(self.id.encode())
        h.update(np.ascontiguousarray(self.vertices).tobytes())
        h.update(np.ascontiguousarray(self.faces.astype(np.int64)).tobytes())
        if self.volume is not None:
            h.update(np.ascontiguousarray(self.volume).tobytes())
            h.update(np.asarray(self.spacing + self.origin).tobytes())
        return h.hexdigest()[:16]
