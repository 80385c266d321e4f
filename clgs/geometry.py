"""Scanner geometry in TIGRE's terms, and the mapping to the internal [-1, 1]^3 scene.

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
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Sequence

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



@dataclass(frozen=True)
class Geometry:
    """A cone- or parallel-beam circular scan. Lengths in mm, angles in radians."""

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

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        if self.mode not in ("cone", "parallel"):
            raise GeometryError(f"mode must be 'cone' or 'parallel', got {self.mode!r}")
        set_("nDetector", _pair("nDetector", self.nDetector, int))
        set_("dDetector", _pair("dDetector", self.dDetector))
        set_("nVoxel", _triple("nVoxel", self.nVoxel, int))
        set_("dVoxel", _triple("dVoxel", self.dVoxel))
        set_("offOrigin", _triple("offOrigin", self.offOrigin))
        set_("offDetector", _pair("offDetector", self.offDetector))
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
        finite = [self.DSD, self.DSO, *self.dDetector, *self.dVoxel, *self.offOrigin, *self.offDetector]
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
        if self.mode == "cone":
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

    # ----------------------------------------------------------------------------- sizes
    @property
    def n_views(self) -> int:
        return int(self.angles.size)

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
        pixel = float(np.min(self.dDetector))
        if self.mode == "cone":
            pixel *= self.DSO / self.DSD
        return min(float(np.min(self.dVoxel)), pixel)

    @property
    def scale(self) -> float:
        """mm -> scene units: the volume's longest side spans 2."""
        return 2.0 / float(np.max(self.sVoxel))

    @property
    def projection_shape(self) -> tuple:
        return (self.n_views, *self.nDetector)

    # ----------------------------------------------------------------------------- mapping
    def world_to_scene(self, points_xyz) -> np.ndarray:
        """mm (x, y, z) -> scene units."""
        return (np.asarray(points_xyz, float) - np.asarray(self.offOrigin[::-1])) * self.scale

    def scene_to_world(self, points_xyz) -> np.ndarray:
        """scene units -> mm (x, y, z)."""
        return np.asarray(points_xyz, float) / self.scale + np.asarray(self.offOrigin[::-1])

    def volume_grid(self, scene: bool = True) -> "Grid":
        """The reconstruction grid, in scene units (default) or mm."""
        spacing = np.asarray(self.dVoxel[::-1], float)
        shape = np.asarray(self.nVoxel, int)
        origin = -0.5 * (shape[::-1] - 1) * spacing  # centre of voxel [0, 0, 0], relative to offOrigin
        if scene:
            return Grid(tuple(shape), tuple(origin * self.scale), tuple(spacing * self.scale))
        return Grid(tuple(shape), tuple(origin + np.asarray(self.offOrigin[::-1])), tuple(spacing))

    # ----------------------------------------------------------------------------- views
    def view_vectors(self, scene: bool = True, views: Sequence[int] | None = None) -> np.ndarray:
        """(n_views, 12) float64: [source or ray direction, detector centre, u step, v step]."""
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
        out = np.concatenate([first, det, du * e_u, dv * e_v], 1)
        if scene:
            origin = np.asarray(self.offOrigin[::-1], float)
            k = self.scale
            if self.mode == "cone":
                out[:, 0:3] = (out[:, 0:3] - origin) * k
            out[:, 3:6] = (out[:, 3:6] - origin) * k
            out[:, 6:12] *= k
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

    def field_of_view(self, margin_px: float = 0.5) -> np.ndarray:
        """(Z, Y, X) bool: the voxels whose centre every view projects onto its detector, at least
        ``margin_px`` pixels inside its edge: where a truncated scan measured every line through
        the voxel (what a reconstruction of a small detector is judged on)."""
        pts = self.volume_grid(scene=False).points().reshape(-1, 3)
        nv, nu = self.nDetector
        inside = np.ones(len(pts), bool)
        for vec in self.view_vectors(scene=False):
            src, det, eu, ev = vec[0:3], vec[3:6], vec[6:9], vec[9:12]
            normal = np.cross(eu, ev)
            if self.mode == "cone":
                d = pts - src
                t = ((det - src) @ normal) / np.where(np.abs(d @ normal) > 1e-12, d @ normal, 1e-12)
                hit = src + t[:, None] * d - det
            else:
                hit = pts - det
            iu = hit @ eu / (eu @ eu) + (nu - 1) / 2.0
            iv = hit @ ev / (ev @ ev) + (nv - 1) / 2.0
            lo, hi_u, hi_v = margin_px - 0.5, nu - 0.5 - margin_px, nv - 0.5 - margin_px
            inside &= (iu >= lo) & (iu <= hi_u) & (iv >= lo) & (iv <= hi_v)
        return inside.reshape(tuple(self.nVoxel))

    # ----------------------------------------------------------------------------- I/O
    def to_dict(self) -> dict:
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
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Geometry":
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
        )

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    def with_angles(self, angles) -> "Geometry":
        d = self.to_dict()
        d["angles"] = list(np.asarray(angles, float).reshape(-1))
        return Geometry.from_dict(d)

    @classmethod
    def default(cls, n_views: int = 50, arc: float = np.pi, mode: str = "cone", n_voxel: int = 128,
                n_detector: int = 256, volume_mm: float = 256.0) -> "Geometry":
        """A scanner sized for a ``volume_mm`` cube, whose detector sees it whole at DSD/DSO = 1.5."""
        DSO, DSD = 1000.0, 1500.0
        mag = DSD / DSO if mode == "cone" else 1.0
        half = 0.5 * volume_mm * np.sqrt(2.0) * mag * 1.05  # corners of the volume, with margin
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

    def block(self, start_zyx, size_zyx) -> "Grid":
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
