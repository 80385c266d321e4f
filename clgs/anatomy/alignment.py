"""Rigid alignment of a bone surface onto a reference surface (optionally mirrored, so a right
bone can be compared with a left model): how a user's mesh is brought into a template's frame."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clgs.errors import InputError


@dataclass
class Alignment:
    """A rigid (optionally mirrored) map of a mesh onto a reference: x' = R (M x) + t, with
    M = diag(-1, 1, 1) when ``mirrored`` (a right bone mapped onto a left reference)."""

    rotation: np.ndarray
    translation: np.ndarray
    mirrored: bool
    rms_mm: float
    iterations: int
    #: with ``allow_scale``: the factor that brings the surface to the reference's size (the
    #: similarity's; 1 / its size relative to the reference), and the RMS distance left once it
    #: is scaled to the reference's size (its shape alone, size set aside); 1.0 and ``rms_mm``
    #: otherwise
    scale: float = 1.0
    shape_rms_mm: float | None = None

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix (mirror included)."""
        m = np.eye(4)
        mir = np.diag([-1.0 if self.mirrored else 1.0, 1.0, 1.0])
        m[:3, :3] = self.rotation @ mir
        m[:3, 3] = self.translation
        return m

    def apply(self, points) -> np.ndarray:
        p = np.asarray(points, float)
        return p @ self.matrix[:3, :3].T + self.translation

    def apply_mesh(self, vertices, faces):
        """Transform a mesh; a mirror reverses the triangles' winding, so faces are flipped back."""
        f = np.asarray(faces)
        return self.apply(vertices), (f[:, ::-1].copy() if self.mirrored else f.copy())


def _kabsch(src, dst, with_scale: bool = False):
    """Least-squares rotation (and, ``with_scale``, isotropic scale: Umeyama's) of ``src`` onto
    ``dst``: (rotation, translation, scale)."""
    cs, cd = src.mean(0), dst.mean(0)
    hmat = (src - cs).T @ (dst - cd)
    uu, sv, vt = np.linalg.svd(hmat)
    dd = np.sign(np.linalg.det(vt.T @ uu.T))
    rot = vt.T @ np.diag([1.0, 1.0, dd]) @ uu.T
    scale = 1.0
    if with_scale:
        scale = float((sv[0] + sv[1] + dd * sv[2]) / max(np.sum((src - cs) ** 2), 1e-30))
    return rot, cd - scale * rot @ cs, scale


def principal_axes(p):
    c = p - p.mean(0)
    evals, evecs = np.linalg.eigh(c.T @ c)
    return evecs[:, ::-1]  # columns: largest variance first


def align_rigid(vertices, reference_vertices, allow_mirror: bool = True, max_iter: int = 60,
                tol: float = 1e-5, max_points: int = 4000, seed: int = 0, allow_scale: bool = False) -> Alignment:
    """Rigidly align a surface (points, mm) to a reference surface in another frame.

    Initial poses: the four proper rotations taking the surface's principal axes onto the
    reference's (PCA sign ambiguity), each refined by ICP (nearest neighbours by KD-tree,
    Kabsch); with ``allow_mirror`` the same again for the mirror image (x -> -x), so a right
    bone is matched to a left reference. The pose with the lowest symmetric RMS distance wins.

    ``allow_scale``: the ICP also fits an isotropic scale (a femur of 550 mm against a template of
    430 mm still finds its pose, and ``shape_rms_mm`` measures its shape, not its size); the
    returned map stays rigid: the rotation found, with the surface's centroid put where the
    scaled fit puts it (a subject keeps its own size)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    mov = np.asarray(vertices, float)
    ref = np.asarray(reference_vertices, float)
    if mov.ndim != 2 or mov.shape[1] != 3 or len(mov) < 4 or ref.ndim != 2 or ref.shape[1] != 3 or len(ref) < 4:
        raise InputError("align_rigid needs two point sets of shape (N>=4, 3)")
    if not (np.all(np.isfinite(mov)) and np.all(np.isfinite(ref))):
        raise InputError("align_rigid: points contain NaN or Inf")
    if len(mov) > max_points:
        mov = mov[rng.choice(len(mov), max_points, replace=False)]
    ref_s = ref[rng.choice(len(ref), max_points, replace=False)] if len(ref) > max_points else ref
    ref_tree = cKDTree(ref)
    e_ref = principal_axes(ref)
    best = None
    for mirrored in ([False, True] if allow_mirror else [False]):
        src = mov * np.array([-1.0 if mirrored else 1.0, 1.0, 1.0])
        e_src = principal_axes(src)
        for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
            rot = e_ref @ np.diag(signs) @ e_src.T
            if np.linalg.det(rot) < 0:
                rot = e_ref @ np.diag(signs) @ np.diag([1, 1, -1]) @ e_src.T
            scale = 1.0
            if allow_scale:  # start from the ratio of the two surfaces' spreads
                scale = float(np.sqrt(((ref - ref.mean(0)) ** 2).sum(1).mean()
                                      / max(((src - src.mean(0)) ** 2).sum(1).mean(), 1e-30)))
            trans = ref.mean(0) - scale * rot @ src.mean(0)
            prev = np.inf
            for it in range(1, max_iter + 1):  # noqa: B007 - the count reached is recorded below
                moved = scale * src @ rot.T + trans
                d, idx = ref_tree.query(moved)
                rot, trans, scale = _kabsch(src, ref[idx], with_scale=allow_scale)
                err = float(np.sqrt(np.mean(d * d)))
                if abs(prev - err) < tol * max(err, 1.0):
                    break
                prev = err
            moved = scale * src @ rot.T + trans
            d1, _ = ref_tree.query(moved)
            d2, _ = cKDTree(moved).query(ref_s)
            rms = float(np.sqrt(0.5 * (np.mean(d1 * d1) + np.mean(d2 * d2))))
            if best is None or rms < best.rms_mm:
                best = Alignment(rot, trans, mirrored, rms, it, scale, rms)
    if allow_scale:  # rigid: the centroid where the scaled fit puts it, the surface's own size
        src = mov * np.array([-1.0 if best.mirrored else 1.0, 1.0, 1.0])
        c = src.mean(0)
        best.translation = best.scale * best.rotation @ c + best.translation - best.rotation @ c
        placed = best.apply(np.asarray(vertices, float))
        d1, _ = ref_tree.query(placed)
        d2, _ = cKDTree(placed).query(ref_s)
        best.rms_mm = float(np.sqrt(0.5 * (np.mean(d1 * d1) + np.mean(d2 * d2))))
    return best
