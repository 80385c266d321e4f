"""Surface meshes on disk: STL, PLY, OBJ (through trimesh) or npz (``vertices``, ``faces``).

Coordinates in memory are clgs's world mm (x, y, z), the frame NIfTI volumes are written in
(labelled RAS). On disk, STL, PLY and OBJ files are written in LPS coordinates (x and y negated)
with ``SPACE=LPS`` in the header (the STL header, a PLY ``comment``, an OBJ ``#`` line): the
convention of DICOM, ITK and 3D Slicer, which reads the tag, so a surface opens aligned with the
volume it came from. On read, a file's tag decides its frame (``SPACE=LPS`` files are turned back
into RAS). A file without a tag is read in the frame ``space`` names; by default LPS, as 3D Slicer
reads untagged files (so a surface exported from Slicer or another ITK-based tool lands where it
was drawn), with a :class:`MeshWarning` naming the frame assumed and how to choose the other
(``space="RAS"``, ``--mesh-space RAS``). npz files are clgs's own arrays, in its world frame.
Writes are atomic. STL stores each triangle's corners separately, so on read coincident vertices
are merged back into a shared-vertex mesh.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from clgs.errors import ClgsError
from clgs.io import atomic

__all__ = ["Mesh", "MeshError", "MeshWarning", "check_mesh", "check_space", "save_mesh", "load_mesh", "mesh_space",
           "MESH_SUFFIXES", "MESH_SPACES", "UNTAGGED_SPACE"]

MESH_SUFFIXES = (".stl", ".ply", ".obj", ".npz")
RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])  # the flip is its own inverse
MESH_SPACES = ("RAS", "LPS")
#: the frame of a surface file with no SPACE= tag, unless the caller names one (3D Slicer's reading)
UNTAGGED_SPACE = "LPS"


class MeshError(ClgsError, ValueError):
    """A mesh file that cannot be read or written as asked."""


class MeshWarning(UserWarning):
    """A surface file read on an assumption (no coordinate tag: the frame assumed is named)."""


class Mesh(NamedTuple):
    """``vertices`` (N, 3) float64 mm (x, y, z); ``faces`` (M, 3) int64 vertex indices."""

    vertices: np.ndarray
    faces: np.ndarray


def check_mesh(vertices, faces, closed: bool = False) -> Mesh:
    """The one check of a triangle mesh (files, templates, phantoms, surfaces): (N, 3) finite
    vertices, (M, 3) integer faces indexing them; returns float64 vertices and int64 faces. With
    ``closed``, every edge must be shared by exactly two faces (a watertight surface has an inside,
    which voxelising needs)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"mesh vertices must be (N, 3) in mm, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and not np.issubdtype(f.dtype, np.integer)):
        raise MeshError(f"mesh faces must be (M, 3) integer vertex indices, got {f.shape} {f.dtype}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise MeshError(f"mesh faces index vertices out of range [0, {len(v)})")
    if not np.all(np.isfinite(v)):
        raise MeshError("mesh vertices contain NaN or Inf")
    if closed:
        if len(v) < 4 or len(f) < 4:
            raise MeshError(f"a closed mesh needs at least 4 vertices and 4 faces, got {len(v)} and {len(f)}")
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(e, axis=0, return_counts=True)
        bad = int(np.sum(counts != 2))
        if bad:
            raise MeshError(f"the mesh is not watertight: {bad} edges are not shared by exactly two faces; "
                            "repair it (e.g. trimesh.repair.fill_holes) before voxelising")
    return Mesh(v, f)


def _suffix(path: Path) -> str:
    suf = path.suffix.lower()
    if suf not in MESH_SUFFIXES:
        raise MeshError(f"{path}: unknown mesh format; use one of {', '.join(MESH_SUFFIXES)}")
    return suf


def save_mesh(path, vertices, faces=None, overwrite: bool = True, scalars: dict | None = None) -> Path:
    """Write a triangle mesh atomically; ``save_mesh(path, mesh)`` also accepts a :class:`Mesh`.
    ``scalars``: name -> one finite value per vertex, written as float vertex properties of a
    binary PLY (the only format here that holds them)."""
    if faces is None:
        vertices, faces = vertices
    path = Path(path)
    suf = _suffix(path)
    mesh = check_mesh(vertices, faces)
    if len(mesh.faces) == 0:
        raise MeshError("the mesh has no faces; nothing to write")
    if scalars and suf != ".ply":
        raise MeshError(f"per-vertex values ({', '.join(scalars)}) are written to PLY only, not {suf}")
    if suf == ".npz":
        return atomic.save_npz(path, overwrite=overwrite, vertices=mesh.vertices, faces=mesh.faces)
    import trimesh

    tm = trimesh.Trimesh(vertices=mesh.vertices * RAS_TO_LPS, faces=mesh.faces, process=False)
    if scalars:
        for name, given in scalars.items():
            values = np.asarray(given, np.float64)
            if values.shape != (len(mesh.vertices),) or not np.isfinite(values).all():
                raise MeshError(f"{name}: need one finite value per vertex ({len(mesh.vertices)}), got {values.shape}")
            tm.vertex_attributes[name] = values.astype(np.float32)
        data = trimesh.exchange.ply.export_ply(tm, encoding="binary", include_attributes=True)
    else:
        data = tm.export(file_type=suf[1:])
    if isinstance(data, str):
        data = data.encode("utf-8")
    return atomic.write_bytes(path, _tagged(data, suf, "LPS"), overwrite=overwrite)


def _tagged(data: bytes, suffix: str, space: str) -> bytes:
    """``data`` (a file as trimesh wrote it) with ``SPACE=<space>`` in its header."""
    tag = f"SPACE={space}"
    if suffix == ".stl":
        if data[:5].lower() == b"solid":  # ASCII STL: the name on the first line
            first, _, rest = data.partition(b"\n")
            return f"solid clgs {tag}".encode() + b"\n" + rest
        header = f"clgs surface mesh {tag}".encode().ljust(80, b" ")  # binary: 80-byte header
        return header + data[80:]
    if suffix == ".ply":
        first, _, rest = data.partition(b"\n")  # "ply"
        fmt, _, rest = rest.partition(b"\n")  # "format ..."
        return b"\n".join([first, fmt, f"comment {tag}".encode(), rest])
    if suffix == ".obj":
        return f"# {tag}\n".encode() + data
    return data


def mesh_space(path) -> str | None:
    """``"LPS"``, ``"RAS"`` or None: the coordinate system a mesh file's header declares."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(4096)
    suf = path.suffix.lower()
    if suf == ".stl":
        head = head[:80] if head[:5].lower() != b"solid" else head.partition(b"\n")[0]
    elif suf == ".ply":
        head = head.partition(b"end_header")[0]
    elif suf == ".obj":
        head = b"\n".join(ln for ln in head.splitlines() if ln.lstrip().startswith(b"#"))
    else:
        return None
    text = head.decode("latin-1").upper().replace(" ", "")
    for space in ("LPS", "RAS"):
        if f"SPACE={space}" in text:
            return space
    return None


def check_space(space, what: str = "space") -> str | None:
    """``space`` as "RAS" or "LPS" (any case), or None; anything else is a MeshError."""
    if space is None:
        return None
    text = str(space).strip().upper()
    if text not in MESH_SPACES:
        raise MeshError(f"{what} {space!r}: give RAS or LPS (the coordinate frame of the surface file)")
    return text


def load_mesh(path, space: str | None = None) -> Mesh:
    """Read a triangle mesh as :class:`Mesh` (vertices mm in clgs's RAS world frame, faces int64).

    A file that declares its frame (``SPACE=LPS`` / ``SPACE=RAS``) is read in it. ``space``
    ("RAS" or "LPS") is the frame of a file that declares none; None reads such a file as
    :data:`UNTAGGED_SPACE` (LPS, as 3D Slicer does) with a :class:`MeshWarning` that says so. A
    tag always wins over ``space`` (a folder may mix tagged and untagged files)."""
    import warnings

    space = check_space(space)
    path = Path(path)
    suf = _suffix(path)
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    if suf == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                if "vertices" not in z or "faces" not in z:
                    raise MeshError(f"{path}: an npz mesh needs arrays 'vertices' and 'faces', has {list(z.keys())}")
                return check_mesh(z["vertices"], z["faces"])
        except MeshError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise MeshError(f"{path}: not a readable npz mesh ({exc})") from exc
    import trimesh

    try:
        tm = trimesh.load(str(path), file_type=suf[1:], force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001
        raise MeshError(f"{path}: not a readable {suf[1:].upper()} mesh ({exc})") from exc
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise MeshError(f"{path}: contains no triangles")
    if suf == ".stl":
        tm.merge_vertices()
    vertices = np.asarray(tm.vertices, dtype=np.float64)
    tag = mesh_space(path)
    if tag is None and space is None:
        warnings.warn(f"{path} declares no coordinate frame (no SPACE=RAS or SPACE=LPS in its header): read as "
                      f"{UNTAGGED_SPACE}, as 3D Slicer reads it; if it is in RAS (e.g. written by earlier clgs "
                      "versions or from a NIfTI's coordinates), pass --mesh-space RAS (Python: space='RAS')",
                      MeshWarning, stacklevel=2)
    if (tag or space or UNTAGGED_SPACE) == "LPS":
        vertices = vertices * RAS_TO_LPS
    return check_mesh(vertices, tm.faces)
