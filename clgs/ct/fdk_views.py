"""What FDK needs to know of each view of a per-view (vector) scan.

FDK's weights are those of a circular orbit. For a scan given view by view, clgs reads that orbit
off the views (the views keep their own source, detector and pixel steps everywhere else):

* the mean rotation axis: its direction is the one most nearly perpendicular to every view's
  central direction (the detector normal, or the ray direction in parallel beam; the eigenvector
  of their scatter matrix with the smallest eigenvalue). Views that all look one way (a single
  view, two opposite views, an arc under about 4 degrees) leave it open: then it is the mean
  detector v axis, made perpendicular to the views' direction. It points along the detector's v
  axis (+z for a circular scan);
* a point on the axis (cone beam): the centre of the least-squares circle through the sources
  seen along the axis; the scanner frame's origin (the isocentre, by the vectors format's
  convention) where fewer than three views or a circle centred farther than half the source
  distance from it (sources on a short or nearly straight arc) make that fit meaningless;
* each view's angle about the axis (the source's azimuth; the ray's in parallel beam) and its
  source's distance from the axis;
* per pixel: the cosine weight ``D / |pixel - source|`` (``D`` the view's source-detector
  distance along the detector normal) and the fan angle ``gamma``: the ray's angle from the
  source-to-axis direction, both seen along the axis, positive towards the detector's u axis
  (``atan(U / DSD)`` of a circular scan).

A circular scan written as vectors gets back its own angles, DSO, DSD, cosine weights and fan
angles (to rounding), so its FDK is the circular one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clgs.geometry import Geometry
from clgs.ops.fdk import view_depths


@dataclass(frozen=True)
class Orbit:
    """The circular orbit FDK's weights assume, read off a per-view scan (scanner frame, mm)."""

    axis: np.ndarray  # (3,) unit direction of the rotation axis
    centre: np.ndarray  # (3,) a point on the axis (its component along the axis is 0)
    angles: np.ndarray  # (n,) each view's angle about the axis, radians, right-handed
    radius: np.ndarray  # (n,) each source's distance from the axis, mm (ones in parallel beam)
    fitted: bool  # whether ``centre`` is the circle fit (else the frame's origin)


def _plane_basis(axis: np.ndarray):
    """Two unit vectors completing ``axis`` to a right-handed frame; the first is world x made
    perpendicular to the axis (or world y, for an axis near x)."""
    ref = np.array([1.0, 0.0, 0.0])
    if np.linalg.norm(ref - (ref @ axis) * axis) < 0.1:
        ref = np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ axis) * axis
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def rotation_axis(geometry: Geometry) -> np.ndarray:
    """The unit direction of the mean rotation axis (module doc)."""
    vec = geometry.frame_vectors()
    dirs, _, _ = view_depths(geometry)
    ev = vec[:, 9:12] / np.linalg.norm(vec[:, 9:12], axis=1, keepdims=True)
    lam, vecs = np.linalg.eigh(dirs.T @ dirs / len(dirs))
    mean_v = ev.sum(0)
    if lam[1] > 1e-3:  # the views turn: the axis is perpendicular to all of them
        axis = vecs[:, 0]
    else:  # all views look one way (or two opposite ways): the detector's v axis
        main = vecs[:, 2]
        axis = mean_v - (mean_v @ main) * main
        if np.linalg.norm(axis) < 1e-6 * len(ev):  # v axes that cancel out (detectors turned both ways)
            axis = vecs[:, 0]
    axis = axis / np.linalg.norm(axis)
    return -axis if axis @ mean_v < 0 else axis


def _circle_centre(points: np.ndarray, typical: float):
    """(centre (2,), fitted) of the least-squares circle through 2D ``points`` (Kasa's algebraic
    fit); the origin where it is not determined or lies farther than ``typical / 2`` from it."""
    uniq = np.unique(np.round(points, 9), axis=0)
    if len(uniq) >= 3:
        a = np.column_stack([2 * points, np.ones(len(points))])
        sol, _, rank, _ = np.linalg.lstsq(a, np.sum(points**2, 1), rcond=None)
        if rank == 3 and np.linalg.norm(sol[:2]) <= 0.5 * typical:
            return sol[:2], True
    return np.zeros(2), False


def orbit(geometry: Geometry) -> Orbit:
    """The mean rotation axis, a point on it, each view's angle about it and its source's distance
    from it (module doc)."""
    vec = geometry.frame_vectors()
    axis = rotation_axis(geometry)
    e1, e2 = _plane_basis(axis)
    if geometry.mode == "cone":
        src = vec[:, 0:3]
        flat = np.stack([src @ e1, src @ e2], 1)
        c2, fitted = _circle_centre(flat, float(np.median(np.linalg.norm(flat, axis=1))))
        rel = flat - c2
        return Orbit(axis, c2[0] * e1 + c2[1] * e2, np.arctan2(rel[:, 1], rel[:, 0]), np.linalg.norm(rel, axis=1),
                     fitted)
    back = -vec[:, 0:3]  # towards the (far) source
    return Orbit(axis, np.zeros(3), np.arctan2(back @ e2, back @ e1), np.ones(len(vec)), False)


def fan_and_cosine(geometry: Geometry, orb: Orbit, view: int, dist: float):
    """(fan angles, cosine weights (V, U)) of one view (module doc); ``dist`` is its source-detector
    distance. The fan angles are (1, U) where the detector's columns run along the axis (they are
    the same on every row), else (V, U). Parallel beam: zeros (1, U) and ones.

    Pixel ``(iv, iu)``'s ray from the source is ``d - s + a u + b v`` (``a``, ``b`` its offsets
    from the detector centre in pixels), so its dot products are sums of a row and a column term."""
    nv, nu = geometry.nDetector
    if geometry.mode != "cone":
        return np.zeros((1, nu)), np.ones((nv, nu))
    row = geometry.frame_vectors([view])[0]
    s, d, eu, ev = row[0:3], row[3:6], row[6:9], row[9:12]
    a = np.arange(nu) - 0.5 * (nu - 1)
    b = (np.arange(nv) - 0.5 * (nv - 1))[:, None]
    c0 = d - s
    r2 = (c0 @ c0 + a * a * (eu @ eu) + 2 * a * (c0 @ eu)) + (b * b * (ev @ ev) + 2 * b * (c0 @ ev)) \
        + 2 * (eu @ ev) * b * a
    cosine = dist / np.sqrt(r2)
    e1, e2 = _plane_basis(orb.axis)
    cc = orb.centre - s
    cx, cy = cc @ e1, cc @ e2
    rx, ry = c0 @ e1 + a * (eu @ e1), c0 @ e2 + a * (eu @ e2)
    if abs(ev @ e1) + abs(ev @ e2) > 1e-12 * np.linalg.norm(ev):  # columns across the axis: per pixel
        rx, ry = rx + b * (ev @ e1), ry + b * (ev @ e2)
    else:
        rx, ry = rx[None], ry[None]
    return np.arctan2(-(cx * ry - cy * rx), cx * rx + cy * ry), cosine
