"""Scanner geometry: a circular scan in TIGRE's terms or any scan as per-view vectors (ASTRA's
``cone_vec`` / ``parallel3d_vec``), and the mapping to the internal [-1, 1]^3 scene.

Conventions (every kernel and reference in clgs follows them):

* Points and direction vectors are (x, y, z). Array shapes and spacings are (Z, Y, X) for
  volumes and (V, U) for detectors, as in TIGRE. Angles are in radians.
* The source turns about the z axis. At angle ``theta`` the unit vector towards the source is
  ``e_s = (cos theta, sin theta, 0)``; the source sits at ``DSO * e_s`` and the detector centre at
  ``-(DSD - DSO) * e_s + offDetector``. The detector's u axis is ``e_u = (-sin theta, cos theta, 0)``
  and its v axis is ``e_v = (0, 0, 1)``: detector row ``iv`` grows with z, column ``iu`` with e_u.
* Pixel ``(iv, iu)`` centre: ``det_centre + (iu - (nU-1)/2) dU e_u + (iv - (nV-1)/2) dV e_v``.
* Voxel ``[k, j, i]`` centre (world, mm): ``offOrigin + ((i-(nX-1)/2) dX, (j-(nY-1)/2) dY, (k-(nZ-1)/2) dZ)``.
* Cone beam: each pixel's ray runs from the source to the pixel centre (only ``t > 0`` counts).
  Parallel beam: each pixel's ray has direction ``-e_s`` and passes through the pixel centre
  (the whole line counts).
* The scene: ``scene = (world - offOrigin) * scale`` with ``scale = 2 / max(nVoxel * dVoxel)``,
  so the volume's longest side spans [-1, 1]. Learning rates and loss weights live in the scene.

``Geometry.view_vectors`` packs each view as 12 numbers (as ASTRA's ``cone_vec``): for cone beam
the source position, for parallel beam the unit ray direction; then the detector centre, the
step of one pixel along u, and the step of one pixel along v, in scene or world units.

Per-view geometry: ``Geometry.from_vectors`` takes those 12 numbers per view in mm (world x, y, z)
directly, so detector offsets, tilts and rolls, C-arm and other non-circular trajectories, irregular
angles and a varying source distance are all one description. Every operator reads the views
through ``view_vectors``; the circular TIGRE description is one way to make them. For a vector
geometry ``DSO``, ``DSD``, ``dDetector`` and ``angles`` are nominal values derived from the vectors
(medians; the source's azimuth), kept for reports, sizing and view ordering only.
"""
from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from clgs.errors import ClgsError, InputError


class GeometryError(ClgsError, ValueError):
    """A scanner geometry that cannot describe a real acquisition."""


def _numbers(name, value) -> np.ndarray:
    """``value`` as a flat float64 array, or a GeometryError naming the field."""
    if isinstance(value, (str, bytes, dict)):
        raise GeometryError(f"{name} must be numbers, got {value!r}")
    try:
        return np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name} must be numbers, got {value!r} ({exc})") from None


def _entries(name, value, n, axes, kind):
    arr = _numbers(name, value)
    if arr.size != n:
        raise GeometryError(f"{name} must have {n} entries ({axes}), got {arr.size}: {value!r}")
    if kind is int and not np.all(np.isfinite(arr) & (arr == np.round(arr))):
        raise GeometryError(f"{name} must be whole numbers of pixels or voxels, got {value!r}")
    return tuple(kind(v) for v in arr)


def _triple(name, value, kind=float):
    return _entries(name, value, 3, "Z, Y, X", kind)


def _pair(name, value, kind=float):
    return _entries(name, value, 2, "V, U", kind)


def _scalar(name, value) -> float:
    arr = _numbers(name, value)
    if arr.size != 1:
        raise GeometryError(f"{name} must be one number, got {value!r}")
    return float(arr[0])

def check_orientation(codes) -> str:
    """Axis codes of a volume file's array axes (i, j, k), as nibabel writes them: three letters,
    one of L/R, one of A/P, one of S/I, in any order (``"RAS"``, ``"LAS"``, ``"LPS"``, ``"PSR"``)."""
    if isinstance(codes, (list, tuple)) and all(isinstance(c, str) for c in codes):
        codes = "".join(codes)
    text = codes if isinstance(codes, str) else None
    if text is None or len(text) != 3:
        raise GeometryError(f"orientation must be three axis codes such as 'RAS' or 'LPS', got {codes!r}")
    text = text.upper()
    pairs = [("L", "R"), ("A", "P"), ("S", "I")]
    if sorted(next((i for i, p in enumerate(pairs) if c in p), 9) for c in text) != [0, 1, 2]:
        raise GeometryError(f"orientation {codes!r}: give one of L/R, one of A/P and one of S/I (e.g. 'LAS')")
    return text


#: How much larger than a volume's shadow a detector sized to see that volume whole is made (the
#: same factor on each axis): the one margin of ``Geometry.default``, ``clgs simulate``'s scanner
#: and the anatomies' scenes.
DETECTOR_MARGIN = 1.05


def shadow_half_extents(size_zyx, DSO: float, DSD: float, mode: str = "cone") -> tuple:
    """(half width u, half height v) in mm on the detector of the shadow of a box of ``size_zyx``
    mm centred on the rotation axis, over every angle: what a detector must span to see the whole
    volume. The in-plane half-diagonal sets the width; in cone beam the box's nearest approach to
    the source sets the magnification of its height."""
    size = np.asarray(size_zyx, np.float64)
    r_xy = 0.5 * float(np.hypot(size[1], size[2]))  # in-plane half-diagonal: the widest shadow
    if mode != "cone":
        return r_xy, 0.5 * size[0]
    if r_xy >= DSO:
        raise GeometryError(f"the volume (in-plane half-diagonal {r_xy:.1f} mm) reaches the source orbit "
                            f"DSO={DSO} mm; increase DSO")
    return DSD * r_xy / math.sqrt(DSO ** 2 - r_xy ** 2), 0.5 * size[0] * DSD / (DSO - r_xy)



def _check_vectors(vectors, mode: str) -> np.ndarray:
    """(n, 12) float64 copy of per-view vectors (mm), or a GeometryError naming the first bad view."""
    if isinstance(vectors, (str, bytes, dict)):
        raise GeometryError(f"vectors must be a list of views of 12 numbers each, got {type(vectors).__name__}")
    try:
        vec = np.array(vectors, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"vectors must be a list of views of 12 numbers each ({exc})") from None
    if vec.ndim != 2 or vec.shape[1] != 12 or vec.shape[0] < 1:
        raise GeometryError(f"vectors must have shape (n_views, 12) with at least one view, got {vec.shape}: "
                            "each view is [source (cone) or ray direction (parallel), detector centre, "
                            "u pixel step, v pixel step], mm")
    first = "source" if mode == "cone" else "ray direction"
    for i, row in enumerate(vec):
        if not np.all(np.isfinite(row)):
            raise GeometryError(f"view {i}: the vector has NaN or Inf entries: {row.tolist()}")
        u, v = row[6:9], row[9:12]
        lu, lv = np.linalg.norm(u), np.linalg.norm(v)
        if lu == 0 or lv == 0:
            raise GeometryError(f"view {i}: zero-length pixel step along {'u' if lu == 0 else 'v'} "
                                "(entries 6-8 are one pixel along u, 9-11 one pixel along v, mm)")
        normal = np.cross(u, v)
        if np.linalg.norm(normal) <= 1e-9 * lu * lv:
            raise GeometryError(f"view {i}: the u and v pixel steps are parallel; the detector has no area")
        normal /= np.linalg.norm(normal)
        if abs(np.dot(u, v)) > 1e-3 * lu * lv:
            raise GeometryError(f"view {i}: the u and v pixel steps are not perpendicular (cosine "
                                f"{np.dot(u, v) / (lu * lv):.2g}); a detector's rows and columns are")
        if mode == "cone":
            depth = float(np.dot(row[3:6] - row[0:3], normal))
            if abs(depth) <= 1e-6 * max(lu, lv):
                raise GeometryError(f"view {i}: the source {row[0:3].tolist()} lies on the detector plane")
        else:
            r = row[0:3]
            lr = np.linalg.norm(r)
            if lr == 0:
                raise GeometryError(f"view {i}: zero-length {first} (entries 0-2)")
            if abs(np.dot(r, normal)) <= 1e-6 * lr:
                raise GeometryError(f"view {i}: the ray direction lies in the detector plane")
            if np.linalg.norm(np.cross(r, normal)) > 1e-6 * lr:
                raise GeometryError(f"view {i}: the parallel rays are not perpendicular to the detector; clgs's "
                                    "parallel beam needs them so (the detector may be turned in its own plane)")
            vec[i, 0:3] = r / lr  # a unit ray direction (its length means nothing)
    return vec


def _nominal(vec: np.ndarray, mode: str) -> dict:
    """Nominal circular values of a vector geometry (see the module doc)."""
    u, v = vec[:, 6:9], vec[:, 9:12]
    out = {"dDetector": (float(np.median(np.linalg.norm(v, axis=1))), float(np.median(np.linalg.norm(u, axis=1)))),
           "offDetector": (0.0, 0.0)}
    if mode == "cone":
        s = vec[:, 0:3]
        normal = np.cross(u, v)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        out["DSO"] = float(np.median(np.linalg.norm(s, axis=1)))
        out["DSD"] = float(np.median(np.abs(np.sum((vec[:, 3:6] - s) * normal, 1))))
        out["angles"] = np.arctan2(s[:, 1], s[:, 0])
    else:
        out["DSO"], out["DSD"] = 1000.0, 1500.0  # unused in parallel beam
        out["angles"] = np.arctan2(-vec[:, 1], -vec[:, 0])
    return out


@dataclass(frozen=True)
class Geometry:
    """A cone- or parallel-beam scan. Lengths in mm, angles in radians.

    Circular (``vectors`` None): TIGRE's description. Per view (``vectors`` an (n_views, 12) array in
    mm, see :meth:`from_vectors`): ``DSD``, ``DSO``, ``dDetector``, ``offDetector`` and ``angles``
    are derived from the vectors (whatever was passed) and are nominal."""

    DSD: float
    DSO: float
    nDetector: tuple  # (V, U) pixels
    dDetector: tuple  # (V, U) mm
    nVoxel: tuple  # (Z, Y, X)
    dVoxel: tuple  # (Z, Y, X) mm
    angles: np.ndarray = field(repr=False)
    offOrigin: tuple = (0.0, 0.0, 0.0)  # (Z, Y, X) mm
    offDetector: tuple = (0.0, 0.0)  # (V, U) mm
    mode: str = "cone"
    #: (Z, Y, X) mm: where the rotation axis crosses the central plane, in the world frame of the
    #: input (a NIfTI's scanner frame, say). Not a TIGRE name: TIGRE puts the isocentre at the
    #: origin. The kernels never see it (they work relative to the volume); it only places what
    #: clgs writes (volumes, surfaces, Gaussians) where the input lay. For a per-view geometry it
    #: is the origin of the vectors' frame in the world.
    isocentre: tuple = (0.0, 0.0, 0.0)
    vectors: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: How volume files of this scan store their array (not a TIGRE name): nibabel's axis codes of
    #: the file's array axes (NIfTI's i, j, k), e.g. ``"LAS"`` (i grows towards the left, j
    #: anterior, k superior) for the input a simulation took. Every array in memory is (Z, Y, X)
    #: along +z, +y, +x (``"RAS"``); writers put the array back in this order, with its affine, so
    #: outputs compare with the input index by index. The kernels never see it.
    orientation: str = "RAS"

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        if self.mode not in ("cone", "parallel"):
            raise GeometryError(f"mode must be 'cone' or 'parallel', got {self.mode!r}")
        if self.vectors is not None:
            vec = _check_vectors(self.vectors, self.mode)
            vec.setflags(write=False)
            set_("vectors", vec)
            for k, v in _nominal(vec, self.mode).items():
                set_(k, v)
        set_("nDetector", _pair("nDetector", self.nDetector, int))
        set_("dDetector", _pair("dDetector", self.dDetector))
        set_("nVoxel", _triple("nVoxel", self.nVoxel, int))
        set_("dVoxel", _triple("dVoxel", self.dVoxel))
        set_("offOrigin", _triple("offOrigin", self.offOrigin))
        set_("offDetector", _pair("offDetector", self.offDetector))
        set_("isocentre", _triple("isocentre", self.isocentre))
        set_("orientation", check_orientation(self.orientation))
        set_("DSD", _scalar("DSD", self.DSD))
        set_("DSO", _scalar("DSO", self.DSO))
        if self.angles is None:
            raise GeometryError("angles are missing (null): a scan needs one angle (radians) per view")
        angles = _numbers("angles", self.angles)
        set_("angles", angles)
        angles.setflags(write=False)
        self.validate()

    # ----------------------------------------------------------------------------- checks
    def validate(self) -> None:
        finite = [self.DSD, self.DSO, *self.dDetector, *self.dVoxel, *self.offOrigin, *self.offDetector,
                  *self.isocentre]
        if not np.all(np.isfinite(finite)):
            raise GeometryError(f"geometry has a non-finite length: {self}")
        if min(self.nDetector) < 1:
            raise GeometryError(f"nDetector must be at least 1 pixel each way, got {self.nDetector}")
        if min(self.nVoxel) < 1:
            raise GeometryError(f"nVoxel must be at least 1 voxel each way, got {self.nVoxel}")
        if min(self.dDetector) <= 0:
            raise GeometryError(f"dDetector (pixel size, mm) must be positive, got {self.dDetector}")
        if min(self.dVoxel) <= 0:
            raise GeometryError(f"dVoxel (voxel size, mm) must be positive, got {self.dVoxel}")
        if self.angles.size == 0:
            raise GeometryError("the angle list is empty: a scan needs at least one view")
        if not np.all(np.isfinite(self.angles)):
            raise GeometryError("angles contain NaN or Inf")
        if self.vectors is not None:
            self._validate_vectors()
        elif self.mode == "cone":
            if self.DSO <= 0 or self.DSD <= 0:
                raise GeometryError(f"DSO and DSD must be positive, got DSO={self.DSO}, DSD={self.DSD}")
            if self.DSO >= self.DSD:
                raise GeometryError(
                    f"DSO ({self.DSO} mm, source to rotation axis) must be smaller than DSD "
                    f"({self.DSD} mm, source to detector): the detector lies beyond the axis"
                )
            # only the in-plane extent can meet the source, which circles in the z = 0 plane
            half_diag = 0.5 * float(np.linalg.norm(self.sVoxel[1:])) + float(np.linalg.norm(self.offOrigin[1:]))
            if half_diag >= self.DSO:
                raise GeometryError(
                    f"the volume (in-plane half-diagonal {half_diag:.1f} mm) reaches the source orbit "
                    f"(DSO={self.DSO} mm): increase DSO or shrink the volume"
                )

    def _validate_vectors(self) -> None:
        """A cone-beam source inside the volume (grown by one voxel) sees no ray through it whole."""
        if self.mode != "cone":
            return
        lo, hi = self.volume_bounds()
        pad = np.asarray(self.dVoxel[::-1], float)
        inside = np.all((self.vectors[:, 0:3] > lo - pad) & (self.vectors[:, 0:3] < hi + pad), axis=1)
        if np.any(inside):
            i = int(np.flatnonzero(inside)[0])
            raise GeometryError(f"view {i}: the source {self.vectors[i, 0:3].tolist()} mm lies inside the volume "
                                f"(x, y, z from {lo.tolist()} to {hi.tolist()} mm, grown by one voxel): move the "
                                "source out or shrink the volume")

    def __eq__(self, other):
        if not isinstance(other, Geometry):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None

    # ----------------------------------------------------------------------------- sizes
    @property
    def n_views(self) -> int:
        return int(self.angles.size)

    @property
    def is_circular(self) -> bool:
        """True for TIGRE's circular description; False for a per-view (vector) geometry, whatever
        trajectory its vectors describe."""
        return self.vectors is None

    def volume_bounds(self) -> tuple:
        """(low, high) corners of the volume in mm, (x, y, z), in the scanner's frame (as
        :meth:`frame_vectors`; add the isocentre for the world)."""
        centre = np.asarray(self.offOrigin[::-1], float)
        half = 0.5 * self.sVoxel[::-1]
        return centre - half, centre + half

    def source_detector_distance(self) -> np.ndarray:
        """(n_views,) mm from the source to the detector plane (cone beam); DSD for every view of a
        circular scan; ones for parallel beam (no magnification)."""
        if self.mode != "cone":
            return np.ones(self.n_views)
        if self.is_circular:
            return np.full(self.n_views, self.DSD)
        vv = self.vectors
        normal = np.cross(vv[:, 6:9], vv[:, 9:12])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        return np.abs(np.sum((vv[:, 3:6] - vv[:, 0:3]) * normal, 1))

    def magnification(self) -> np.ndarray:
        """(n_views,) detector magnification of the volume's centre (source-detector distance over
        source-centre depth along the detector normal); ones for parallel beam."""
        if self.mode != "cone":
            return np.ones(self.n_views)
        vv = self.frame_vectors()
        normal = np.cross(vv[:, 6:9], vv[:, 9:12])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        centre = np.asarray(self.offOrigin[::-1], float)
        dsd = np.abs(np.sum((vv[:, 3:6] - vv[:, 0:3]) * normal, 1))
        if self.is_circular:  # the rotation axis, as TIGRE
            return dsd / self.DSO
        return dsd / np.abs(np.sum((centre - vv[:, 0:3]) * normal, 1))

    @property
    def sVoxel(self) -> np.ndarray:
        """Volume size in mm, (Z, Y, X)."""
        return np.asarray(self.nVoxel, float) * np.asarray(self.dVoxel, float)

    @property
    def sDetector(self) -> np.ndarray:
        """Detector size in mm, (V, U)."""
        return np.asarray(self.nDetector, float) * np.asarray(self.dDetector, float)

    @property
    def resolution_mm(self) -> float:
        """The finest spacing the scan samples, in mm: the smallest voxel side or detector pixel seen
        at the rotation axis (pixel x DSO / DSD in cone beam). Structure finer than this is not in
        the data; it sets the smallest Gaussian a reconstruction may use."""
        if self.is_circular:
            pixel = float(np.min(self.dDetector))
            if self.mode == "cone":
                pixel *= self.DSO / self.DSD
        else:
            vec = self.vectors
            steps = np.minimum(np.linalg.norm(vec[:, 6:9], axis=1), np.linalg.norm(vec[:, 9:12], axis=1))
            pixel = float(np.min(steps / self.magnification()))
        return min(float(np.min(self.dVoxel)), pixel)

    @property
    def scale(self) -> float:
        """mm -> scene units: the volume's longest side spans 2."""
        return 2.0 / float(np.max(self.sVoxel))

    @property
    def projection_shape(self) -> tuple:
        return (self.n_views, *self.nDetector)

    @property
    def centre_xyz(self) -> np.ndarray:
        """The volume's centre in world mm (x, y, z): the isocentre plus TIGRE's offOrigin."""
        return np.asarray(self.isocentre[::-1], float) + np.asarray(self.offOrigin[::-1], float)

    # ----------------------------------------------------------------------------- mapping
    def world_to_scene(self, points_xyz) -> np.ndarray:
        """mm (x, y, z) -> scene units."""
        return (np.asarray(points_xyz, float) - self.centre_xyz) * self.scale

    def scene_to_world(self, points_xyz) -> np.ndarray:
        """scene units -> mm (x, y, z)."""
        return np.asarray(points_xyz, float) / self.scale + self.centre_xyz

    def volume_grid(self, scene: bool = True) -> Grid:
        """The reconstruction grid, in scene units (default) or mm."""
        spacing = np.asarray(self.dVoxel[::-1], float)
        shape = np.asarray(self.nVoxel, int)
        origin = -0.5 * (shape[::-1] - 1) * spacing  # centre of voxel [0, 0, 0], relative to offOrigin
        if scene:
            return Grid(tuple(shape), tuple(origin * self.scale), tuple(spacing * self.scale))
        return Grid(tuple(shape), tuple(origin + self.centre_xyz), tuple(spacing))

    # ----------------------------------------------------------------------------- views
    def view_vectors(self, scene: bool = True, views: Sequence[int] | None = None) -> np.ndarray:
        """(n_views, 12) float64: [source or ray direction, detector centre, u step, v step], in
        scene units relative to the volume (default), or in world mm (the isocentre added)."""
        return self._placed(self.frame_vectors(views), scene)

    def frame_vectors(self, views: Sequence[int] | None = None) -> np.ndarray:
        """(n_views, 12) float64 vectors in mm in the scanner's own frame (TIGRE's: the isocentre at
        the origin, the volume's centre at ``offOrigin``): the circular description's, or the given
        per-view ones."""
        if self.vectors is not None:
            return np.array(self.vectors if views is None else self.vectors[np.asarray(views, int)], np.float64)
        th = self.angles if views is None else self.angles[np.asarray(views, int)]
        c, s = np.cos(th), np.sin(th)
        z = np.zeros_like(th)
        e_s = np.stack([c, s, z], 1)
        e_u = np.stack([-s, c, z], 1)
        e_v = np.stack([z, z, z + 1.0], 1)
        dv, du = self.dDetector
        ov, ou = self.offDetector
        det = -(self.DSD - self.DSO) * e_s + ou * e_u + ov * e_v
        first = self.DSO * e_s if self.mode == "cone" else -e_s
        return np.concatenate([first, det, du * e_u, dv * e_v], 1)

    def _placed(self, out: np.ndarray, scene: bool) -> np.ndarray:
        """Scanner-frame vectors ``out`` (changed in place) in scene units or world mm."""
        if scene:
            origin = np.asarray(self.offOrigin[::-1], float)
            k = self.scale
            if self.mode == "cone":
                out[:, 0:3] = (out[:, 0:3] - origin) * k
            out[:, 3:6] = (out[:, 3:6] - origin) * k
            out[:, 6:12] *= k
        elif any(self.isocentre):
            iso = np.asarray(self.isocentre[::-1], float)
            if self.mode == "cone":
                out[:, 0:3] += iso
            out[:, 3:6] += iso
        return out

    def rays(self, view: int, scene: bool = True):
        """Reference ray of every pixel of one view: (origins (V,U,3), unit directions (V,U,3)).

        Cone: origin is the source, integrate over t > 0. Parallel: origin is the pixel centre,
        integrate over all t. Plain NumPy, for tests and references.
        """
        vec = self.view_vectors(scene=scene, views=[view])[0]
        nv, nu = self.nDetector
        iu = np.arange(nu) - (nu - 1) / 2.0
        iv = np.arange(nv) - (nv - 1) / 2.0
        pix = vec[3:6] + iu[None, :, None] * vec[6:9] + iv[:, None, None] * vec[9:12]
        if self.mode == "cone":
            d = pix - vec[0:3]
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            return np.broadcast_to(vec[0:3], pix.shape).copy(), d
        return pix, np.broadcast_to(vec[0:3], pix.shape).copy()

    def detector_pixels(self, points_xyz, view: int) -> tuple:
        """Where world points (N, 3) mm land on one view's detector: (column, row) pixel indices as
        floats (pixel centres at integers; off the detector below -0.5 or above n - 0.5)."""
        pts = np.asarray(points_xyz, float).reshape(-1, 3)
        vec = self.view_vectors(scene=False, views=[view])[0]
        src, det, eu, ev = vec[0:3], vec[3:6], vec[6:9], vec[9:12]
        if self.mode == "cone":
            normal = np.cross(eu, ev)
            d = pts - src
            dn = d @ normal
            t = ((det - src) @ normal) / np.where(np.abs(dn) > 1e-12, dn, 1e-12)
            hit = src + t[:, None] * d - det
        else:
            hit = pts - det
        nv, nu = self.nDetector
        return hit @ eu / (eu @ eu) + (nu - 1) / 2.0, hit @ ev / (ev @ ev) + (nv - 1) / 2.0

    def field_of_view(self, margin_px: float = 0.5) -> np.ndarray:
        """(Z, Y, X) bool: the voxels whose centre every view projects onto its detector, at least
        ``margin_px`` pixels inside its edge: where a truncated scan measured every line through
        the voxel (what a reconstruction of a small detector is judged on)."""
        pts = self.volume_grid(scene=False).points().reshape(-1, 3)
        nv, nu = self.nDetector
        inside = np.ones(len(pts), bool)
        for view in range(self.n_views):
            iu, iv = self.detector_pixels(pts, view)
            lo, hi_u, hi_v = margin_px - 0.5, nu - 0.5 - margin_px, nv - 0.5 - margin_px
            inside &= (iu >= lo) & (iu <= hi_u) & (iv >= lo) & (iv <= hi_v)
        return inside.reshape(tuple(self.nVoxel))

    # ----------------------------------------------------------------------------- I/O
    def to_dict(self) -> dict:
        """JSON-ready: TIGRE's names for a circular scan, ``vectors`` (and no DSO, DSD, angles) for a
        per-view one."""
        if self.vectors is not None:
            return {"mode": self.mode, "nDetector": list(self.nDetector), "nVoxel": list(self.nVoxel),
                    "dVoxel": list(self.dVoxel), "offOrigin": list(self.offOrigin),
                    **({"isocentre": list(self.isocentre)} if any(self.isocentre) else {}),
                    **({"orientation": self.orientation} if self.orientation != "RAS" else {}),
                    "vectors": [[float(x) for x in row] for row in self.vectors]}
        return {
            "mode": self.mode,
            "DSD": self.DSD,
            "DSO": self.DSO,
            "nDetector": list(self.nDetector),
            "dDetector": list(self.dDetector),
            "nVoxel": list(self.nVoxel),
            "dVoxel": list(self.dVoxel),
            "offOrigin": list(self.offOrigin),
            "offDetector": list(self.offDetector),
            "angles": [float(a) for a in self.angles],
            **({"isocentre": list(self.isocentre)} if any(self.isocentre) else {}),
            **({"orientation": self.orientation} if self.orientation != "RAS" else {}),
        }

    @classmethod
    def from_vectors(cls, vectors, nDetector, nVoxel, dVoxel, offOrigin=(0.0, 0.0, 0.0),
                     mode: str = "cone", isocentre=(0.0, 0.0, 0.0), orientation: str = "RAS") -> Geometry:
        """A per-view geometry: ``vectors`` (n_views, 12) in mm, (x, y, z), ASTRA's order per view:
        source (cone) or ray direction (parallel), detector centre, one pixel along u (columns), one
        pixel along v (rows). They share the frame of ``offOrigin`` (the volume's centre); the
        optional ``isocentre`` places that frame in the world, as for a circular scan."""
        if vectors is None:
            raise GeometryError("vectors are missing (null): give (n_views, 12) numbers")
        if mode not in ("cone", "parallel"):
            raise GeometryError(f"mode must be 'cone' or 'parallel', got {mode!r}")
        vec = _check_vectors(vectors, mode)
        return cls(DSD=1.0, DSO=0.5, nDetector=nDetector, dDetector=(1.0, 1.0), nVoxel=nVoxel, dVoxel=dVoxel,
                   angles=np.zeros(len(vec)), offOrigin=offOrigin, mode=mode, isocentre=isocentre, vectors=vec,
                   orientation=orientation)

    def as_vectors(self) -> Geometry:
        """The same scan as a per-view geometry (the circular description written as vectors)."""
        return Geometry.from_vectors(self.frame_vectors(), self.nDetector, self.nVoxel, self.dVoxel,
                                     self.offOrigin, self.mode, self.isocentre, self.orientation)

    def select(self, views) -> Geometry:
        """The geometry of the views ``views`` (indices, in that order)."""
        idx = np.asarray(views, int).reshape(-1)
        if self.vectors is not None:
            return Geometry.from_vectors(self.vectors[idx], self.nDetector, self.nVoxel, self.dVoxel,
                                         self.offOrigin, self.mode, self.isocentre, self.orientation)
        return self.with_angles(self.angles[idx])

    @classmethod
    def from_dict(cls, d: dict) -> Geometry:
        if not isinstance(d, dict):
            raise GeometryError(f"a geometry must be a JSON object, got {type(d).__name__}")
        if "vectors" in d:
            missing = [k for k in ("nDetector", "nVoxel", "dVoxel") if k not in d]
            if missing:
                raise GeometryError(f"geometry is missing {', '.join(missing)} (needed beside vectors)")
            g = cls.from_vectors(d["vectors"], d["nDetector"], d["nVoxel"], d["dVoxel"],
                                 d.get("offOrigin", (0, 0, 0)), d.get("mode", "cone"), d.get("isocentre", (0, 0, 0)),
                                 d.get("orientation", "RAS"))
            n_angles = _numbers("angles", d["angles"]).size if d.get("angles") is not None else g.n_views
            if n_angles != g.n_views:
                raise GeometryError(f"geometry has {n_angles} angles but {g.n_views} vectors: give one vector per "
                                    "view (angles are not needed beside vectors)")
            return g
        required = ("DSD", "DSO", "nDetector", "dDetector", "nVoxel", "dVoxel", "angles")
        missing = [k for k in required if k not in d]
        if missing:
            raise GeometryError(f"geometry is missing {', '.join(missing)}")
        return cls(
            DSD=d["DSD"],
            DSO=d["DSO"],
            nDetector=d["nDetector"],
            dDetector=d["dDetector"],
            nVoxel=d["nVoxel"],
            dVoxel=d["dVoxel"],
            angles=d["angles"],
            offOrigin=d.get("offOrigin", (0, 0, 0)),
            offDetector=d.get("offDetector", (0, 0)),
            mode=d.get("mode", "cone"),
            isocentre=d.get("isocentre", (0, 0, 0)),
            orientation=d.get("orientation", "RAS"),
        )

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    def with_angles(self, angles) -> Geometry:
        if self.vectors is not None:
            raise GeometryError("a per-view (vector) geometry has no angles to replace; use select(views)")
        d = self.to_dict()
        d["angles"] = list(np.asarray(angles, float).reshape(-1))
        return Geometry.from_dict(d)

    def binned(self, factor: int) -> Geometry:
        """The same scan seen by a detector whose ``factor`` x ``factor`` pixel blocks are one pixel
        (the detector's extent, centre and every view unchanged; its sides must be multiples of
        ``factor``). What coarse-to-fine training renders early (:mod:`clgs.fit.schedule`)."""
        f = int(factor)
        nv, nu = self.nDetector
        if f < 1 or nv % f or nu % f:
            raise GeometryError(f"a {nv} x {nu} detector cannot be binned by {factor}: its sides must be multiples")
        if f == 1:
            return self
        if self.vectors is not None:
            vec = np.array(self.vectors, dtype=np.float64)
            vec[:, 6:12] *= f  # pixel steps along u and v; the detector centre stays
            return Geometry.from_vectors(vec, (nv // f, nu // f), self.nVoxel, self.dVoxel, self.offOrigin,
                                         self.mode, self.isocentre, self.orientation)
        return dataclasses.replace(self, nDetector=(nv // f, nu // f),
                                   dDetector=tuple(float(d) * f for d in self.dDetector))

    @classmethod
    def default(cls, n_views: int = 50, arc: float = np.pi, mode: str = "cone", n_voxel: int = 128,
                n_detector: int = 256, volume_mm: float = 256.0) -> Geometry:
        """A scanner sized for a ``volume_mm`` cube, whose detector sees it whole at DSD/DSO = 1.5."""
        DSO, DSD = 1000.0, 1500.0
        mag = DSD / DSO if mode == "cone" else 1.0
        half = 0.5 * volume_mm * np.sqrt(2.0) * mag * DETECTOR_MARGIN  # corners of the volume, with margin
        d_det = 2 * half / n_detector
        angles = np.linspace(0.0, arc, n_views, endpoint=False) if n_views > 0 else []
        return cls(DSD=DSD, DSO=DSO, nDetector=(n_detector, n_detector), dDetector=(d_det, d_det),
                   nVoxel=(n_voxel,) * 3, dVoxel=(volume_mm / n_voxel,) * 3, angles=angles, mode=mode)


@dataclass(frozen=True)
class Grid:
    """A regular grid of sample points: ``shape`` (Z, Y, X), ``origin`` = centre of voxel
    [0, 0, 0] as (x, y, z), ``spacing`` as (dx, dy, dz)."""

    shape: tuple
    origin: tuple
    spacing: tuple

    def block(self, start_zyx, size_zyx) -> Grid:
        """The axis-aligned sub-block starting at voxel ``start_zyx`` with ``size_zyx`` voxels."""
        start = np.asarray(start_zyx, int)
        size = np.asarray(size_zyx, int)
        if np.any(start < 0) or np.any(start + size > np.asarray(self.shape)) or np.any(size < 1):
            raise InputError(f"block {tuple(start)}+{tuple(size)} does not fit in grid {self.shape}")
        origin = np.asarray(self.origin) + start[::-1] * np.asarray(self.spacing)
        return Grid(tuple(int(s) for s in size), tuple(origin), self.spacing)

    def points(self) -> np.ndarray:
        """All sample points, (Z, Y, X, 3) as (x, y, z)."""
        axes = [self.origin[a] + self.spacing[a] * np.arange(self.shape[2 - a]) for a in range(3)]
        z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        return np.stack([x, y, z], -1)


def read_geometry(path, grid: dict | None = None) -> Geometry:
    """A geometry from a JSON file: TIGRE's names for a circular scan or ``vectors`` for a per-view
    one (docs/formats.md), bare or under a ``geometry`` key (as in a scan folder's scan.json).
    ``grid``: ``nVoxel``, ``dVoxel`` and/or ``offOrigin`` that replace the file's (a simulation's
    volume brings its own grid; the file then only needs the scanner). Errors name the file."""
    from pathlib import Path

    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise GeometryError(f"{p}: cannot read the geometry file ({exc})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise GeometryError(f"{p}: not a JSON file ({exc})") from None
    if isinstance(doc, dict) and isinstance(doc.get("geometry"), dict):
        doc = doc["geometry"]
    if isinstance(doc, dict) and grid:
        doc = {**doc, **{k: list(v) for k, v in grid.items()}}
    try:
        return Geometry.from_dict(doc)
    except GeometryError as exc:
        raise GeometryError(f"{p}: {exc}") from None
