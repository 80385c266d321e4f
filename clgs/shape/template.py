"""Anatomy templates and population subjects on regular grids in mm.

Conventions (shared with :mod:`clgs.shape.model`):

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
import zipfile
from dataclasses import dataclass, field

import numpy as np

from clgs.errors import InputError
from clgs.io.mesh import check_mesh
from clgs.mesh import voxels as meshvol

TEMPLATE_FORMAT = "clgs.template"
TEMPLATE_VERSION = 1


# --------------------------------------------------------------------------------------- grids
def zyx_triple(name, value, dtype=float):
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be 3 finite numbers (Z, Y, X), got {value!r}")
    return tuple(dtype(v) for v in arr)


def grid_points(shape, spacing, origin) -> np.ndarray:
    """All voxel centres of a grid as an array (Z, Y, X, 3) of (x, y, z) in mm."""
    shape = zyx_triple("shape", shape, int)
    spacing, origin = zyx_triple("spacing", spacing), zyx_triple("origin", origin)
    axes = [origin[a] + spacing[a] * np.arange(shape[a]) for a in range(3)]  # z, y, x axes
    z, y, x = np.meshgrid(*axes, indexing="ij")
    return np.stack([x, y, z], -1)


def box_grid(lo_xyz, hi_xyz, max_cells: int = None, spacing: float = None):
    """A grid (shape, spacing, origin) covering the box [lo, hi] (x, y, z mm) with isotropic cells.

    Either ``max_cells`` (cells along the longest side) or ``spacing`` (mm) sets the resolution."""
    lo, hi = np.asarray(lo_xyz, float), np.asarray(hi_xyz, float)
    size = hi - lo
    if np.any(size <= 0):
        raise InputError(f"empty box: lo={lo}, hi={hi}")
    if spacing is None:
        if not max_cells or max_cells < 2:
            raise InputError("give max_cells >= 2 or a spacing in mm")
        spacing = float(size.max()) / (max_cells - 1)
    n = np.maximum(np.ceil(size / spacing).astype(int) + 1, 2)
    centre = 0.5 * (lo + hi)
    origin_xyz = centre - 0.5 * (n - 1) * spacing
    return (tuple(int(v) for v in n[::-1]), (float(spacing),) * 3, tuple(float(v) for v in origin_xyz[::-1]))


def sample_volume(volume, spacing, origin, points, fill: float | None = 0.0, order: int = 1) -> np.ndarray:
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
    """(float64 vertices, int64 faces); open meshes are accepted here (a template's surface from
    marching cubes may touch its grid's border), closedness is checked where an inside is needed."""
    return check_mesh(vertices, faces, closed=False)


def _grid(shape, spacing, origin):
    """This module's (Z, Y, X) shape/spacing/origin as a :class:`clgs.geometry.Grid` (x, y, z)."""
    from clgs.geometry import Grid

    shape = zyx_triple("shape", shape, int)
    spacing, origin = zyx_triple("spacing", spacing), zyx_triple("origin", origin)
    return Grid(shape, origin[::-1], spacing[::-1])


def mesh_to_label(vertices, faces, shape, spacing, origin) -> np.ndarray:
    """Inside/outside (bool, Z, Y, X) of a closed triangle mesh on a grid given as (Z, Y, X)
    ``shape``/``spacing``/``origin``: :func:`clgs.mesh.voxels.mesh_to_label` (exact ray parity)."""
    return meshvol.mesh_to_label(vertices, faces, _grid(shape, spacing, origin))


def mesh_to_sdf(vertices, faces, shape, spacing, origin, label=None, band_cells: float = 3.0) -> np.ndarray:
    """Signed distance (float32 mm, negative inside) of a closed mesh on a (Z, Y, X) grid:
    :func:`clgs.mesh.voxels.signed_distance`, exact within ``band_cells`` voxels of the surface
    (``label``: the mesh's inside on this grid, when already known)."""
    return meshvol.signed_distance((vertices, faces), _grid(shape, spacing, origin), band_voxels=band_cells,
                                   label=label)


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
        raise InputError(f"the volume has no {level} iso-surface (range {sdf.min()}..{sdf.max()})")
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


def save_npz_atomic(path, arrays: dict):
    """Compressed npz, written atomically (:func:`clgs.io.atomic.save_npz`)."""
    from clgs.io import atomic

    atomic.save_npz(path, compressed=True, **arrays)


def json_array(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj, sort_keys=True).encode("utf-8"), dtype=np.uint8).copy()


def json_from_array(arr) -> dict:
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
    normals: np.ndarray | None = None
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.spacing = zyx_triple("spacing", self.spacing)
        self.origin = zyx_triple("origin", self.origin)
        if min(self.spacing) <= 0:
            raise InputError(f"template spacing must be positive, got {self.spacing}")
        self.sdf = np.asarray(self.sdf, np.float32)
        self.label = np.asarray(self.label, bool)
        if self.sdf.ndim != 3 or self.label.shape != self.sdf.shape:
            raise InputError(f"template label {self.label.shape} and sdf {self.sdf.shape} must be the "
                             "same (Z, Y, X) shape")
        if not np.all(np.isfinite(self.sdf)):
            raise InputError("template signed distance contains NaN or Inf")
        self.vertices, self.faces = _check_mesh(self.vertices, self.faces)
        if self.normals is None:
            self.normals = vertex_normals(self.vertices, self.faces)
        self.normals = np.asarray(self.normals, np.float32)
        if self.normals.shape != self.vertices.shape:
            raise InputError(f"normals {self.normals.shape} must match vertices {self.vertices.shape}")

    # ---- construction
    @classmethod
    def from_mesh(cls, vertices, faces, spacing: float = 2.0, margin: float = 10.0, name: str = "",
                  shape=None, origin=None, meta=None) -> Template:
        """Voxelise a closed surface: a grid of isotropic ``spacing`` mm around it with ``margin`` mm
        on every side (or the given ``shape``/``origin``)."""
        v, f = _check_mesh(vertices, faces)
        if shape is None:
            shape, sp, origin = box_grid(v.min(0) - margin, v.max(0) + margin, spacing=float(spacing))
        else:
            sp = zyx_triple("spacing", spacing if np.ndim(spacing) else (spacing,) * 3)
            if origin is None:
                raise InputError("give origin together with shape")
        label = mesh_to_label(v, f, shape, sp, origin)
        sdf = mesh_to_sdf(v, f, shape, sp, origin, label=label)
        return cls(label, sdf, v, f, sp, origin, name=name, meta=dict(meta or {}))

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
        """One npz (format ``clgs.shape.template``), written atomically."""
        meta = {"format": TEMPLATE_FORMAT, "version": TEMPLATE_VERSION, "name": self.name, "meta": self.meta}
        save_npz_atomic(path, dict(
            label=self.label.astype(np.uint8), sdf=self.sdf, vertices=self.vertices, faces=self.faces,
            normals=self.normals, spacing=np.asarray(self.spacing), origin=np.asarray(self.origin),
            metadata=json_array(meta)))

    @classmethod
    def load(cls, path) -> Template:
        try:
            return cls._load(path)
        except ValueError:
            raise
        except (OSError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise InputError(f"cannot read template file {path} ({exc}): reinstall the anatomy plugin or "
                             "rebuild the template") from exc

    @classmethod
    def _load(cls, path) -> Template:
        with np.load(path, allow_pickle=False) as z:
            if "metadata" not in z.files:
                raise InputError(f"{path} is not a clgs template (no metadata)")
            meta = json_from_array(z["metadata"])
            if meta.get("format") != TEMPLATE_FORMAT:
                raise InputError(f"{path} is not a clgs template (format {meta.get('format')!r})")
            if meta.get("version", 0) > TEMPLATE_VERSION:
                raise InputError(f"{path} is template format version {meta['version']}; this clgs reads "
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
    volume: np.ndarray | None = None
    spacing: tuple | None = None
    origin: tuple | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.id = str(self.id)
        self.vertices, self.faces = _check_mesh(self.vertices, self.faces)
        if self.volume is not None:
            self.volume = np.asarray(self.volume, np.float32)
            if self.volume.ndim != 3:
                raise InputError(f"subject {self.id}: volume must be (Z, Y, X), got {self.volume.shape}")
            if self.spacing is None or self.origin is None:
                raise InputError(f"subject {self.id}: a volume needs its spacing and origin (Z, Y, X mm)")
            self.spacing = zyx_triple("spacing", self.spacing)
            self.origin = zyx_triple("origin", self.origin)

    def sdf_on(self, shape, spacing, origin) -> np.ndarray:
        """Signed distance (mm) of the subject's surface on a grid."""
        return mesh_to_sdf(self.vertices, self.faces, shape, spacing, origin)

    def volume_at(self, points, fill: float | None = 0.0) -> np.ndarray:
        """CT values at points (..., 3) (x, y, z mm), trilinear; ``fill`` (default 0, air) outside
        the volume, or the nearest border value when ``fill`` is None."""
        if self.volume is None:
            raise InputError(f"subject {self.id} has no CT volume")
        return sample_volume(self.volume, self.spacing, self.origin, points, fill=fill)

    def content_hash(self) -> str:
        h = hashlib.sha256(self.id.encode())
        h.update(np.ascontiguousarray(self.vertices).tobytes())
        h.update(np.ascontiguousarray(self.faces.astype(np.int64)).tobytes())
        if self.volume is not None:
            h.update(np.ascontiguousarray(self.volume).tobytes())
            h.update(np.asarray(self.spacing + self.origin).tobytes())
        return h.hexdigest()[:16]
