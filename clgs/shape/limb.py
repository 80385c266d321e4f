"""The limb's outline measured in the views, and the density atlas's tissue carried onto it.

From few views the free Gaussians cannot tell where the limb's edge runs between the lines that
graze it: two views leave a box where the limb is round, and the atlas's tissue, the prior there,
is the population's limb (its own girth, its edge blurred by every limb's; its variance so large
at the edge that the prior lets go there). But each view's silhouette does say where the limb's
edge is: per slice along the leg, the lines from the source through the silhouette's two edges
graze the limb, and the ellipse (axes along x and y, as the atlas's limb) tangent to every
view's lines is the limb's outline where the views cannot see it. The same fit on the atlas's
tissue (its extents along the views' detector directions) gives the atlas's outline; a per-slice
similarity (a shift and a scale along x and along y) carries the one onto the other.

:class:`LimbWarp` holds both outlines and gives the map, for the density prior (the atlas read
where the scan's edge corresponds to the atlas's, and, where the outline was measured, the
atlas's variance across limbs no longer counted: once the edge is placed, the population's
spread of edges is not this scan's uncertainty) and for the free Gaussians' start (carried from
the atlas's outline onto the scan's). Near the bone the map blends to the identity (the bone and
the tissue next to it are the shape model's and the atlas's own).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clgs.errors import InputError
from clgs.shape.size import LEG_AXIS

#: a detector pixel is inside the limb's silhouette where its line integral is above this share of
#: the view's 99th percentile (on the femur's scans about 0.1: a chord of some 5 mm of tissue, which
#: lies within about 0.05 mm of the edge of a limb 120 mm across)
EDGE_FRACTION = 0.03
#: the scan's outline against the atlas's, per axis, at most this factor either way (beyond it the
#: slice is taken as unmeasured: a silhouette cut by something else than the limb)
MAX_RATIO = 1.4
#: the map is the identity within the first distance of the template's bone surface and whole
#: beyond the second (mm), smooth in between
BLEND_MM = (5.0, 15.0)
#: slices the outlines are smoothed over along the leg (Gaussian sigma, in slices)
SMOOTH_SLICES = 1.5
#: the least singular value of the views' detector directions (unit rows) for an ellipse fit:
#: below it the views look along one line (one view, or views a half-turn apart)
MIN_SPREAD = 0.25


@dataclass(frozen=True)
class Ellipses:
    """Per slice along the leg: position (mm), centre (x, y) mm, radii (x, y) mm, and whether the
    slice was measured (elsewhere the values are meaningless)."""

    z: np.ndarray  # (Z,)
    centre: np.ndarray  # (Z, 2)
    radii: np.ndarray  # (Z, 2)
    valid: np.ndarray  # (Z,) bool


def view_directions(geometry) -> np.ndarray:
    """(V, 2): each view's detector u direction within a slice (x, y), unit; rows of zeros where a
    view's detector runs along the leg."""
    vec = geometry.frame_vectors()
    u = vec[:, 6:8].copy()
    n = np.linalg.norm(u, axis=1, keepdims=True)
    return np.where(n > 1e-9 * np.linalg.norm(vec[:, 6:9], axis=1, keepdims=True), u / np.maximum(n, 1e-300), 0.0)


def spread_ok(directions: np.ndarray) -> bool:
    """Whether the views' directions span a slice well enough for an ellipse (:data:`MIN_SPREAD`)."""
    d = np.asarray(directions, float)
    d = d[np.linalg.norm(d, axis=1) > 0.5]
    if len(d) < 2:
        return False
    quad = np.stack([d[:, 0] ** 2, d[:, 1] ** 2], 1)  # the radii's least squares
    return bool(np.linalg.svd(d, compute_uv=False)[-1] >= MIN_SPREAD
                and np.linalg.svd(quad, compute_uv=False)[-1] >= MIN_SPREAD ** 2)


def fit_ellipses(mask: np.ndarray, grid, directions: np.ndarray, usable: np.ndarray | None = None) -> Ellipses:
    """The axis-aligned ellipse per slice (Z) of a (Z, Y, X) mask on ``grid`` (clgs.geometry.Grid,
    mm) whose extents along each of ``directions`` ((V, 2) unit, zeros skipped) are the mask's
    (its support values: ``u . c +- sqrt(a^2 u_x^2 + b^2 u_y^2)``, least squares). ``usable``
    (Z,) bool: slices that may be measured at all. A slice is invalid where the mask is empty,
    touches the grid's side, or a fit leaves a radius not positive."""
    mask = np.asarray(mask, bool)
    nz, ny, nx = mask.shape
    xs = grid.origin[0] + grid.spacing[0] * np.arange(nx)
    ys = grid.origin[1] + grid.spacing[1] * np.arange(ny)
    zs = grid.origin[2] + grid.spacing[2] * np.arange(nz)
    d = np.asarray(directions, float)
    d = d[np.linalg.norm(d, axis=1) > 0.5]
    # the outermost voxel centres lie about half a voxel inside the edge along the grid's axes
    half_voxel = 0.5 * np.maximum(np.abs(d[:, 0]) * grid.spacing[0], np.abs(d[:, 1]) * grid.spacing[1])
    quad = np.stack([d[:, 0] ** 2, d[:, 1] ** 2], 1)
    centre = np.zeros((nz, 2))
    radii = np.ones((nz, 2))
    valid = np.zeros(nz, bool)
    usable = np.ones(nz, bool) if usable is None else np.asarray(usable, bool)
    if len(d) < 2:
        return Ellipses(zs, centre, radii, valid)
    for k in range(nz):
        sl = mask[k]
        if not usable[k] or not sl.any() or sl[0].any() or sl[-1].any() or sl[:, 0].any() or sl[:, -1].any():
            continue
        j, i = np.nonzero(sl)
        along = xs[i][None, :] * d[:, 0:1] + ys[j][None, :] * d[:, 1:2]  # (V, N)
        lo, hi = along.min(1) - half_voxel, along.max(1) + half_voxel
        c = np.linalg.lstsq(d, 0.5 * (lo + hi), rcond=None)[0]
        q = np.linalg.lstsq(quad, (0.5 * (hi - lo)) ** 2, rcond=None)[0]
        valid[k] = bool(np.all(q > 0))
        if valid[k]:
            centre[k], radii[k] = c, np.sqrt(q)
    return Ellipses(zs, centre, radii, valid)


def silhouettes(projections: np.ndarray, fraction: float = EDGE_FRACTION) -> np.ndarray:
    """(V, rows, cols) bool: the pixels each view sees something through (above ``fraction`` of the
    view's 99th percentile; a 3 x 3 median clears single noisy pixels)."""
    from scipy.ndimage import median_filter

    p = np.asarray(projections, np.float32)
    out = np.empty(p.shape, bool)
    for v in range(len(p)):
        level = fraction * float(np.percentile(p[v], 99))
        out[v] = median_filter(p[v] > max(level, 0.0), size=3, mode="nearest") if level > 0 else False
    return out


def _edge_lines(geometry, masks: np.ndarray, z: np.ndarray, centre_xy) -> tuple:
    """Per view and slice, the two lines within the slice (outward unit normal n (2,), offset d:
    ``n . x = d``) from the source through the silhouette's edges, in the detector row the slice's
    ``centre_xy`` projects to; (normals (V, Z, 2, 2), offsets (V, Z, 2), usable (V, Z)). A row is
    not usable where it is off the detector, empty, or its silhouette reaches the detector's side
    (a truncated view)."""
    nv, nu = geometry.nDetector
    nz, nviews = len(z), geometry.n_views
    normals = np.zeros((nviews, nz, 2, 2))
    offsets = np.zeros((nviews, nz, 2))
    usable = np.zeros((nviews, nz), bool)
    centres = np.stack([np.full(nz, centre_xy[0]), np.full(nz, centre_xy[1]), z], 1)
    vecs = geometry.view_vectors(scene=False)
    for view in range(nviews):
        src, det, eu, ev = (vecs[view, i:i + 3] for i in (0, 3, 6, 9))
        eu_xy = eu[:2]
        if np.linalg.norm(eu_xy) < 1e-9 * np.linalg.norm(eu):
            continue
        _, iv = geometry.detector_pixels(centres, view)
        for k in range(nz):
            row = int(np.rint(iv[k]))
            if not 0 <= row < nv:
                continue
            cols = np.flatnonzero(masks[view][row])
            if cols.size == 0 or cols[0] == 0 or cols[-1] == nu - 1:
                continue
            for side, col, sign in ((0, cols[0] - 0.5, -1.0), (1, cols[-1] + 0.5, 1.0)):
                edge = det + (col - (nu - 1) / 2.0) * eu + (row - (nv - 1) / 2.0) * ev
                along = (edge - src)[:2] if geometry.mode == "cone" else src[:2]
                t = along / max(np.linalg.norm(along), 1e-300)
                n = np.array([-t[1], t[0]])
                n = n if sign * (n @ eu_xy) > 0 else -n
                normals[view, k, side], offsets[view, k, side] = n, n @ edge[:2]
            usable[view, k] = True
    return normals, offsets, usable


def _tangent_fit(normals: np.ndarray, offsets: np.ndarray, start) -> tuple | None:
    """(centre (2,), radii (2,)) of the axis-aligned ellipse tangent to lines ``n . x = d``
    (outward unit normals): ``n . c + sqrt(a^2 n_x^2 + b^2 n_y^2) = d``, least squares; None when
    the lines do not pin it (:func:`spread_ok`) or the fit fails."""
    from scipy.optimize import least_squares

    if not spread_ok(normals):
        return None

    def res(p):
        c, r = p[:2], p[2:]
        return normals @ c + np.sqrt((normals ** 2) @ (r ** 2)) - offsets

    fit = least_squares(res, np.asarray(start, float), bounds=([-np.inf, -np.inf, 1e-3, 1e-3], np.inf))
    return (fit.x[:2], fit.x[2:]) if fit.success and np.all(np.isfinite(fit.x)) else None


def scan_outline(scan) -> Ellipses:
    """The limb's outline in a scan's views (module doc), per slice of the scan's grid: the ellipse
    tangent to the lines from the source through each view's silhouette edges (cone beam: exact
    where the limb's cross-section changes slowly along the leg). A slice is measured only where
    every view's row is usable (:func:`_edge_lines`) and the views spread (:data:`MIN_SPREAD`)."""
    geo = scan.geometry
    grid = geo.volume_grid(scene=False)
    nz = geo.nVoxel[0]
    z = grid.origin[2] + grid.spacing[2] * np.arange(nz)
    middle = np.asarray(grid.origin, float) + 0.5 * np.asarray(grid.spacing, float) * (np.asarray(geo.nVoxel[::-1]) - 1)
    normals, offsets, usable = _edge_lines(geo, silhouettes(scan.projections), z, middle[:2])
    centre, radii, valid = np.zeros((nz, 2)), np.ones((nz, 2)), np.zeros(nz, bool)
    for k in range(nz):
        if not usable[:, k].all():
            continue
        n = normals[:, k].reshape(-1, 2)
        d = offsets[:, k].reshape(-1)
        half = max(0.5 * float(np.mean(offsets[:, k].sum(1))), 1.0)  # each pair's half-width
        fit = _tangent_fit(n, d, [middle[0], middle[1], half, half])
        if fit is not None:
            centre[k], radii[k], valid[k] = fit[0], fit[1], True
    return Ellipses(z, centre, radii, valid)


def tissue_level(atlas, template, away_mm: float = 15.0) -> tuple[float, float]:
    """(the atlas's tissue density, its variance there): medians over the atlas's voxels more than
    ``away_mm`` from the template's bone where the mean is above half of that region's 90th
    percentile (the limb's inside)."""
    pts = atlas.grid().points().reshape(-1, 3)
    far = template.sdf_at(pts) > away_mm
    mean, var = atlas.mean.reshape(-1)[far], atlas.var.reshape(-1)[far]
    if not (mean > 0).any():
        raise InputError("the density atlas holds no tissue away from the bone: no limb outline to carry")
    inside = mean > 0.5 * float(np.percentile(mean[mean > 0], 90))
    return float(np.median(mean[inside])), float(np.median(var[inside]))


def atlas_outline(atlas, level: float, directions) -> Ellipses:
    """The atlas's limb outline in the template's frame (module doc): the atlas's mean above half
    its tissue ``level`` (:func:`tissue_level`), fitted along the scan's view ``directions``."""
    return fit_ellipses(atlas.mean > 0.5 * level, atlas.grid(), directions)


def blend_of_distance(d):
    """The carry's blend at signed distances ``d`` (mm) from the template's bone: 0 within
    :data:`BLEND_MM`[0], 1 beyond [1], smoothstep between (NumPy or torch)."""
    t = ((d - BLEND_MM[0]) / (BLEND_MM[1] - BLEND_MM[0])).clip(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(values, sigma, axis=0, mode="nearest") if sigma > 0 and len(values) > 1 else values


class LimbWarp:
    """Points of the scan's limb carried onto the atlas's (module doc). ``scan``: the scan's
    outline (subject frame); ``atlas``: the atlas's (template frame), placed in the subject frame
    per use by the tissue's scaling (:meth:`placed`)."""

    def __init__(self, scan: Ellipses, atlas: Ellipses, template, variance: float):
        self.scan, self.atlas, self.template = scan, atlas, template
        self.variance = float(variance)  # the atlas's variance inside the limb (tissue_level)

    @property
    def measured(self) -> float:
        """The share of the scan's slices whose outline was measured."""
        return float(np.mean(self.scan.valid)) if len(self.scan.valid) else 0.0

    def placed(self, centre_mm, across: float = 1.0, along: float = 1.0) -> dict:
        """Per slice of the scan: the shift and scale taking the scan's outline onto the atlas's,
        the atlas's outline carried into the subject frame by ``x -> c + diag(across, across,
        along) (x - c)`` about ``centre_mm`` (the tissue's scaling), and the weight (0..1) of the
        measured slices; smoothed along the leg. Keys: z, c_scan, c_atlas, ratio, weight."""
        c = np.asarray(centre_mm, float)
        s, a = self.scan, self.atlas
        # the atlas's slice at each scan slice: z_t = c_z + (z - c_z) / along
        zt = c[LEG_AXIS] + (s.z - c[LEG_AXIS]) / float(along)
        inside = (zt >= a.z.min()) & (zt <= a.z.max())
        a_valid = np.interp(zt, a.z, a.valid.astype(float)) > 0.999
        ca = np.stack([np.interp(zt, a.z, a.centre[:, i]) for i in range(2)], 1)
        ra = np.stack([np.interp(zt, a.z, a.radii[:, i]) for i in range(2)], 1)
        ca = c[None, :2] + across * (ca - c[None, :2])
        ra = across * ra
        ok = s.valid & a_valid & inside
        ratio = np.ones_like(ra)
        ratio[ok] = ra[ok] / s.radii[ok]
        ok &= np.all((ratio <= MAX_RATIO) & (ratio >= 1.0 / MAX_RATIO), axis=1)
        ratio[~ok] = 1.0
        c_scan = np.where(ok[:, None], s.centre, ca)
        shift = np.where(ok[:, None], ca - s.centre, 0.0)
        log_ratio = _smooth(np.log(ratio), SMOOTH_SLICES)
        weight = _smooth(ok.astype(float), SMOOTH_SLICES)
        c_scan = _smooth(c_scan, SMOOTH_SLICES)
        shift = _smooth(shift, SMOOTH_SLICES)
        return {"z": s.z, "c_scan": c_scan, "c_atlas": c_scan + shift, "ratio": np.exp(log_ratio), "weight": weight}

    def blend(self, template_points) -> np.ndarray:
        """0 within :data:`BLEND_MM`[0] of the template's bone, 1 beyond [1], smooth between (at
        points of the template's frame)."""
        return blend_of_distance(self.template.sdf_at(np.asarray(template_points, float)))

    @staticmethod
    def _at(placed: dict, z) -> tuple:
        zz = np.asarray(z, float)
        cs = np.stack([np.interp(zz, placed["z"], placed["c_scan"][:, i]) for i in range(2)], -1)
        ct = np.stack([np.interp(zz, placed["z"], placed["c_atlas"][:, i]) for i in range(2)], -1)
        r = np.stack([np.interp(zz, placed["z"], placed["ratio"][:, i]) for i in range(2)], -1)
        w = np.interp(zz, placed["z"], placed["weight"])
        return cs, ct, r, w

    def _carry(self, placed: dict, points_mm, blend, inverse: bool) -> tuple:
        """(the points carried, the per-axis factor across the leg (N, 2), the slices' measured
        weight (N,)): the scan's outline onto the atlas's, or back with ``inverse``; blended."""
        p = np.asarray(points_mm, float)
        cs, ct, r, w = self._at(placed, p[:, LEG_AXIS])
        axes = [a for a in range(3) if a != LEG_AXIS]
        moved = cs + (p[:, axes] - ct) / r if inverse else ct + (p[:, axes] - cs) * r
        b = np.asarray(blend, float)[:, None]
        out = p.copy()
        out[:, axes] = p[:, axes] + b * (moved - p[:, axes])
        return out, 1.0 + b * ((1.0 / r if inverse else r) - 1.0), w

    def to_atlas(self, placed: dict, points_mm: np.ndarray, blend: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points of the scan carried onto the atlas's limb, the weight of the carry: ``blend``
        times the slice's measured weight), points (N, 3) mm of the subject frame."""
        out, _, w = self._carry(placed, points_mm, blend, inverse=False)
        return out, np.asarray(blend, float) * w

    def from_atlas(self, placed: dict, points_mm: np.ndarray, blend: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points of the atlas's limb carried onto the scan's, the per-axis factor across the leg
        (N, 2) their extents take), the inverse of :meth:`to_atlas` at ``blend`` 1; blended as it."""
        out, factor, _ = self._carry(placed, points_mm, blend, inverse=True)
        return out, factor
