"""Surface to CT phantom: voxelise a closed bone surface and fill it with tissue densities.

Nothing here knows which bone it is given: an anatomy plugin passes its surfaces, its grid and a
:class:`DensityParams` (cortex thickness profile, cancellous texture, canal, limb size).

Grids are :class:`clgs.geometry.Grid` (``shape`` (Z, Y, X), ``origin`` = centre of voxel
[0, 0, 0] as (x, y, z) mm, ``spacing`` (dx, dy, dz) mm). Points are (x, y, z) mm. Volumes are
(Z, Y, X). Signed distances are mm, negative inside.

Density model (values are linear attenuation coefficients in 1/mm at an effective energy of
70 keV; approximate values, log-log interpolated between the 60 and 80 keV entries of the
NIST X-ray mass attenuation coefficient tables (Hubbell and Seltzer, NIST XCOM data) for the
ICRU Report 44 tissue compositions, times the ICRU 44 mass densities):

==============================  ========  =================================================
tissue                          mu (/mm)  source (approximate, 70 keV)
==============================  ========  =================================================
cortical bone (rho 1.92)        0.050     NIST/XCOM "Bone, Cortical (ICRU-44)" 0.262 cm2/g
cancellous (trabecular) bone    0.027     marrow + ~20% bone volume fraction (BV/TV) mix of
                                          the cortical and marrow values (ICRU 44 spongiosa
                                          density ~1.18 g/cm3 gives the same)
yellow marrow (medullary canal) 0.0185    adipose-like (ICRU-44 adipose 0.189 cm2/g) at
                                          rho ~0.98 (ICRP yellow marrow)
skeletal muscle (rho 1.05)      0.0202    NIST/XCOM "Muscle, Skeletal (ICRU-44)" 0.193 cm2/g
adipose tissue (rho 0.95)       0.0180    NIST/XCOM "Adipose Tissue (ICRU-44)" 0.189 cm2/g
skin (rho 1.09)                 0.0209    NIST/XCOM "Skin (ICRU-44)" 0.192 cm2/g
air (rho 0.0012)                0.0       2e-5 /mm in the tables; set to 0 (vacuum outside)
==============================  ========  =================================================

(Water for comparison: 0.0194 /mm at 70 keV.) Partial volumes are modelled: a voxel cut by a
tissue boundary gets the mix of both values in proportion to the fraction of the voxel on
each side (from the signed distances), as a CT scanner would record it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

# the surface -> label / signed distance steps live in clgs.mesh.voxels (shared with clgs.shape.template)
from clgs.io.mesh import check_mesh
from clgs.mesh.voxels import as_grid, grid_axes, mesh_to_label, signed_distance

# version of the phantom model: part of the key of cached models built from phantoms
PHANTOM_VERSION = 2

# tissue codes of the label map returned with every phantom (dominant tissue per voxel)
AIR, SKIN, FAT, MUSCLE, MARROW, TRABECULAR, CORTICAL = range(7)
TISSUE_NAMES = ("air", "skin", "fat", "muscle", "marrow", "trabecular", "cortical")


# --------------------------------------------------------------------------------------- grids
def grid_around(lo_xyz, hi_xyz, spacing: float, multiple: int = 8):
    """An isotropic Grid of ``spacing`` mm centred on the box [lo, hi] (x, y, z mm) that covers
    it, each size rounded up to a multiple of ``multiple`` voxels (friendly to tiled kernels)."""
    from clgs.geometry import Grid

    lo, hi = np.asarray(lo_xyz, float), np.asarray(hi_xyz, float)
    if np.any(hi <= lo):
        raise ValueError(f"empty box: lo={lo}, hi={hi}")
    n = np.ceil((hi - lo) / spacing).astype(int)
    n = np.maximum(multiple * np.ceil(n / multiple).astype(int), multiple)
    centre = 0.5 * (lo + hi)
    origin = centre - 0.5 * (n - 1) * spacing
    return Grid(tuple(int(v) for v in n[::-1]), tuple(float(v) for v in origin), (float(spacing),) * 3)


# --------------------------------------------------------------------------------------- alignment
@dataclass
class Alignment:
    """A rigid (optionally mirrored) map of a mesh onto a reference: x' = R (M x) + t, with
    M = diag(-1, 1, 1) when ``mirrored`` (a right bone mapped onto a left reference)."""

    rotation: np.ndarray
    translation: np.ndarray
    mirrored: bool
    rms_mm: float
    iterations: int

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


def _kabsch(src, dst):
    cs, cd = src.mean(0), dst.mean(0)
    hmat = (src - cs).T @ (dst - cd)
    uu, _, vt = np.linalg.svd(hmat)
    dd = np.sign(np.linalg.det(vt.T @ uu.T))
    rot = vt.T @ np.diag([1.0, 1.0, dd]) @ uu.T
    return rot, cd - rot @ cs


def _pca_axes(p):
    c = p - p.mean(0)
    evals, evecs = np.linalg.eigh(c.T @ c)
    return evecs[:, ::-1]  # columns: largest variance first


def align_rigid(vertices, reference_vertices, allow_mirror: bool = True, max_iter: int = 60,
                tol: float = 1e-5, max_points: int = 4000, seed: int = 0) -> Alignment:
    """Rigidly align a surface (points, mm) to a reference surface in another frame.

    Initial poses: the four proper rotations taking the surface's principal axes onto the
    reference's (PCA sign ambiguity), each refined by ICP (nearest neighbours by KD-tree,
    Kabsch); with ``allow_mirror`` the same again for the mirror image (x -> -x), so a right
    bone is matched to a left reference. The pose with the lowest symmetric RMS distance wins."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    mov = np.asarray(vertices, float)
    ref = np.asarray(reference_vertices, float)
    if mov.ndim != 2 or mov.shape[1] != 3 or len(mov) < 4 or ref.ndim != 2 or ref.shape[1] != 3 or len(ref) < 4:
        raise ValueError("align_rigid needs two point sets of shape (N>=4, 3)")
    if not (np.all(np.isfinite(mov)) and np.all(np.isfinite(ref))):
        raise ValueError("align_rigid: points contain NaN or Inf")
    if len(mov) > max_points:
        mov = mov[rng.choice(len(mov), max_points, replace=False)]
    ref_s = ref[rng.choice(len(ref), max_points, replace=False)] if len(ref) > max_points else ref
    ref_tree = cKDTree(ref)
    e_ref = _pca_axes(ref)
    best = None
    for mirrored in ([False, True] if allow_mirror else [False]):
        src = mov * np.array([-1.0 if mirrored else 1.0, 1.0, 1.0])
        e_src = _pca_axes(src)
        for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
            rot = e_ref @ np.diag(signs) @ e_src.T
            if np.linalg.det(rot) < 0:
                rot = e_ref @ np.diag(signs) @ np.diag([1, 1, -1]) @ e_src.T
            trans = ref.mean(0) - rot @ src.mean(0)
            prev = np.inf
            for it in range(1, max_iter + 1):
                moved = src @ rot.T + trans
                d, idx = ref_tree.query(moved)
                rot, trans = _kabsch(src, ref[idx])
                err = float(np.sqrt(np.mean(d * d)))
                if abs(prev - err) < tol * max(err, 1.0):
                    break
                prev = err
            moved = src @ rot.T + trans
            d1, _ = ref_tree.query(moved)
            d2, _ = cKDTree(moved).query(ref_s)
            rms = float(np.sqrt(0.5 * (np.mean(d1 * d1) + np.mean(d2 * d2))))
            if best is None or rms < best.rms_mm:
                best = Alignment(rot, trans, mirrored, rms, it)
    return best


# --------------------------------------------------------------------------------------- density
@dataclass(frozen=True)
class SoftTissue:
    """A limb around the bone: per z slice an ellipse that encloses the bone's cross-section with
    ``margin_mm`` of muscle (at least ``min_semi_axes_mm`` (x, y)), centred on the bone's
    cross-section plus ``offset_mm`` (x, y), covered by ``fat_mm`` of fat and ``skin_mm`` of skin."""

    min_semi_axes_mm: tuple = (70.0, 65.0)
    margin_mm: float = 25.0
    offset_mm: tuple = (0.0, 0.0)
    fat_mm: float = 12.0
    skin_mm: float = 2.0
    smooth_mm: float = 25.0  # how smoothly the limb follows the bone along z


@dataclass(frozen=True)
class DensityParams:
    """Tissue values (linear attenuation, 1/mm, at ``energy_kev``) and the bone's inner structure.

    Cortex thickness along the bone's long axis (position t in [0, 1] between its ends):
    ``cortex_end_mm`` at the ends rising to ``cortex_mid_mm`` over the central
    ``2 * cortex_plateau`` of the length. The medullary canal (marrow) fills the inside of the
    central ``2 * canal_plateau`` (0: no canal), lined by ``canal_lining_mm`` of cancellous bone.
    Cancellous bone elsewhere inside: ``trabecular`` times (1 + band-limited seeded noise of
    relative std ``texture_amplitude`` and correlation ``texture_scale_mm``), denser by
    ``subchondral_boost`` just under the cortex, clipped to ``trabecular_range``.
    ``variation``: relative std devs of the per-subject factors (see :func:`vary_params`)."""

    energy_kev: float = 70.0
    cortical: float = 0.050
    trabecular: float = 0.027
    marrow: float = 0.0185
    muscle: float = 0.0202
    fat: float = 0.0180
    skin: float = 0.0209
    air: float = 0.0
    cortex_mid_mm: float = 5.5
    cortex_end_mm: float = 1.5
    cortex_plateau: float = 0.22
    canal_plateau: float = 0.25
    canal_lining_mm: float = 2.0
    end_softness: float = 0.05
    texture_amplitude: float = 0.08
    texture_scale_mm: float = 2.0
    subchondral_boost: float = 0.10
    trabecular_range: tuple = (0.022, 0.032)
    cortical_range: tuple = (0.045, 0.056)
    soft_tissue: SoftTissue = field(default_factory=SoftTissue)
    variation: dict = field(default_factory=lambda: {"cortex": 0.10, "bmd": 0.04, "soft": 0.08, "fat": 0.25})

    def ranges(self) -> dict:
        """Value range (1/mm) of every tissue when a voxel holds that tissue alone."""
        return {"air": (self.air, self.air), "skin": (self.skin, self.skin), "fat": (self.fat, self.fat),
                "muscle": (self.muscle, self.muscle), "marrow": (self.marrow, self.marrow),
                "trabecular": tuple(self.trabecular_range), "cortical": tuple(self.cortical_range)}


def vary_params(params: DensityParams, seed: int) -> DensityParams:
    """A subject's own parameters: seeded factors on cortex thickness, bone mineral density
    (cortical and cancellous values, within their ranges), muscle margin and fat thickness."""
    rng = np.random.default_rng([int(seed), 0x5EED])
    var = params.variation
    g = lambda key: float(np.clip(rng.normal(0.0, var.get(key, 0.0)), -2.5 * var.get(key, 0.0),  # noqa: E731
                                  2.5 * var.get(key, 0.0)))
    cortex = 1.0 + g("cortex")
    bmd = 1.0 + g("bmd")
    soft = 1.0 + g("soft")
    fat = 1.0 + g("fat")
    st = params.soft_tissue
    st = dataclasses.replace(st, margin_mm=st.margin_mm * soft,
                             min_semi_axes_mm=tuple(a * soft for a in st.min_semi_axes_mm),
                             fat_mm=st.fat_mm * fat)
    lo_c, hi_c = params.cortical_range
    lo_t, hi_t = params.trabecular_range
    return dataclasses.replace(
        params, cortex_mid_mm=params.cortex_mid_mm * cortex, cortex_end_mm=params.cortex_end_mm * cortex,
        cortical=float(np.clip(params.cortical * bmd, lo_c, hi_c)),
        trabecular=float(np.clip(params.trabecular * bmd, lo_t, hi_t)), soft_tissue=st)


def band_limited_noise(shape, spacing_zyx, scale_mm: float, seed: int) -> np.ndarray:
    """Zero-mean, unit-std Gaussian noise smoothed with a Gaussian of ``scale_mm`` (float32)."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng([int(seed), 0x7E87])
    n = rng.standard_normal(shape).astype(np.float32)
    sigma = [max(scale_mm / s, 0.5) for s in spacing_zyx]
    n = gaussian_filter(n, sigma=sigma, mode="wrap")
    sd = float(n.std())
    return n / sd if sd > 0 else n


def long_axis(label, grid):
    """(centre (3,), unit direction (3,), half-length mm) of the principal axis of a label's voxels
    (direction with non-negative z, so that t = 0 is the lower end)."""
    kk, jj, ii = np.nonzero(label)
    if kk.size < 4:
        raise ValueError("the label has fewer than 4 voxels: cannot find its long axis")
    xs, ys, zs = grid_axes(grid)
    p = np.stack([xs[ii], ys[jj], zs[kk]], 1)
    c = p.mean(0)
    d = _pca_axes(p)[:, 0]
    if d[2] < 0:
        d = -d
    s = (p - c) @ d
    half = 0.5 * (s.max() - s.min())
    centre = c + d * 0.5 * (s.max() + s.min())
    return centre, d, float(half)


def _plateau(t, half_width, softness):
    """1 in the middle of [0, 1], falling smoothly to 0 at |t - 0.5| = half_width."""
    if half_width <= 0:
        return np.zeros_like(t)
    s = np.clip((half_width - np.abs(t - 0.5)) / max(softness, 1e-6) + 0.5, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)  # smoothstep over a transition of width ``softness``


def _ramp(x, h):
    """Fraction of a voxel of size h on the inside of a boundary at signed depth x (linear)."""
    return np.clip(0.5 + x / h, 0.0, 1.0)


def limb_distance(label, grid, soft: SoftTissue) -> np.ndarray:
    """Approximate signed distance (mm, negative inside) to the limb's elliptic outline, per slice."""
    from scipy.ndimage import gaussian_filter1d, maximum_filter1d

    nz, ny, nx = grid.shape
    xs, ys, zs = grid_axes(grid)
    any_y = label.any(axis=2)  # (Z, Y)
    any_x = label.any(axis=1)  # (Z, X)
    has = any_y.any(1)
    if not has.any():
        raise ValueError("the bone label is empty: nothing to wrap soft tissue around")
    big = 1e9
    ylo = np.where(any_y, ys[None, :], big).min(1)
    yhi = np.where(any_y, ys[None, :], -big).max(1)
    xlo = np.where(any_x, xs[None, :], big).min(1)
    xhi = np.where(any_x, xs[None, :], -big).max(1)
    idx = np.arange(nz)
    src = idx[has]
    near = src[np.clip(np.searchsorted(src, idx), 0, len(src) - 1)]
    # slices beyond the bone take the nearest bone slice's outline
    prev = src[np.clip(np.searchsorted(src, idx, side="right") - 1, 0, len(src) - 1)]
    near = np.where(np.abs(prev - idx) <= np.abs(near - idx), prev, near)
    cx, cy = 0.5 * (xlo + xhi)[near], 0.5 * (ylo + yhi)[near]
    hx, hy = 0.5 * (xhi - xlo)[near], 0.5 * (yhi - ylo)[near]
    sig = soft.smooth_mm / grid.spacing[2]
    if sig > 0 and nz > 1:
        cx, cy = gaussian_filter1d(cx, sig, mode="nearest"), gaussian_filter1d(cy, sig, mode="nearest")
        # a smooth envelope of the half-extents (running maximum, then smoothed) that never dips
        # below the slice's own bone extent, so the limb has no steps where the bone widens
        win = 2 * int(np.ceil(2 * sig)) + 1
        hx = np.maximum(gaussian_filter1d(maximum_filter1d(hx, win, mode="nearest"), sig, mode="nearest"), hx)
        hy = np.maximum(gaussian_filter1d(maximum_filter1d(hy, win, mode="nearest"), sig, mode="nearest"), hy)
    cover = soft.margin_mm + soft.fat_mm + soft.skin_mm
    # inner ellipse (bone side of the cover), then grown per slice until it holds every bone voxel
    ai = np.maximum(soft.min_semi_axes_mm[0] - cover, abs(soft.offset_mm[0]) + hx)
    bi = np.maximum(soft.min_semi_axes_mm[1] - cover, abs(soft.offset_mm[1]) + hy)
    cx = cx + soft.offset_mm[0]
    cy = cy + soft.offset_mm[1]
    X = xs[None, None, :] - cx[:, None, None]
    Y = ys[None, :, None] - cy[:, None, None]
    rr = np.sqrt((X / ai[:, None, None]) ** 2 + (Y / bi[:, None, None]) ** 2)
    grow = np.maximum(np.where(label, rr, 0.0).max(axis=(1, 2)), 1.0)
    if sig > 0 and nz > 1:
        win = 2 * int(np.ceil(2 * sig)) + 1
        grow = np.maximum(gaussian_filter1d(maximum_filter1d(grow, win, mode="nearest"), sig, mode="nearest"), grow)
    a = ai * grow + cover
    b = bi * grow + cover
    A, B = a[:, None, None], b[:, None, None]
    r = np.sqrt((X / A) ** 2 + (Y / B) ** 2)
    grad = np.sqrt((X / A**2) ** 2 + (Y / B**2) ** 2)
    # first-order distance to the ellipse (exact on the axes of a circle); r / |grad r| at the centre
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.where(grad > 0, (r - 1.0) * r / np.maximum(grad, 1e-12), -np.minimum(A, B) + 0 * r)
    return d.astype(np.float32)


def density_volume(label, sdf, grid, params: DensityParams = DensityParams(), seed: int = 0, axis=None,
                   return_fractions: bool = False):
    """CT-like attenuation volume (float32 1/mm, (Z, Y, X)) and dominant-tissue map (int8, codes
    AIR..CORTICAL) of a bone given its label and signed distance on ``grid``.

    ``axis``: optional (centre, unit direction, half-length) of the long axis along which the
    cortex thickness and the canal vary (default: principal axis of the label). Deterministic:
    the same inputs and ``seed`` give the same bits. With ``return_fractions`` also the
    fraction of every voxel held by each tissue, (7, Z, Y, X) float32 in code order."""
    grid = as_grid(grid)
    label = np.asarray(label, bool)
    sdf = np.asarray(sdf, np.float32)
    if label.shape != tuple(grid.shape) or sdf.shape != tuple(grid.shape):
        raise ValueError(f"label {label.shape} and sdf {sdf.shape} must both have the grid's shape {grid.shape}")
    if not np.all(np.isfinite(sdf)):
        raise ValueError("the signed distance contains NaN or Inf")
    p = params
    spacing_zyx = tuple(float(s) for s in grid.spacing[::-1])
    h = float(np.mean(spacing_zyx))
    xs, ys, zs = grid_axes(grid)
    centre, direction, half = long_axis(label, grid) if axis is None else axis
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    s = ((xs[None, None, :] - centre[0]) * direction[0] + (ys[None, :, None] - centre[1]) * direction[1]
         + (zs[:, None, None] - centre[2]) * direction[2])
    t = np.clip(0.5 + s / (2.0 * max(half, 1e-6)), 0.0, 1.0).astype(np.float32)
    cortex = p.cortex_end_mm + (p.cortex_mid_mm - p.cortex_end_mm) * _plateau(t, p.cortex_plateau, p.end_softness)
    canal = _plateau(t, p.canal_plateau, p.end_softness)

    depth = -sdf  # mm inside the bone surface
    f_bone = _ramp(depth, h)
    f_inner = _ramp(depth - cortex, h)  # beyond the cortex
    f_canal = canal * _ramp(depth - cortex - p.canal_lining_mm, h)
    noise = band_limited_noise(grid.shape, spacing_zyx, p.texture_scale_mm, seed)
    sub = 1.0 + p.subchondral_boost * np.exp(-np.maximum(depth - cortex, 0.0) / 4.0)
    trab = np.clip(p.trabecular * sub * (1.0 + p.texture_amplitude * noise), *p.trabecular_range)
    cort = np.float32(np.clip(p.cortical, *p.cortical_range))

    st = p.soft_tissue
    d_limb = limb_distance(label, grid, st)
    f_limb = _ramp(-d_limb, h)
    f_fat = _ramp(-(d_limb + st.skin_mm), h)
    f_muscle = _ramp(-(d_limb + st.skin_mm + st.fat_mm), h)

    soft = (p.air * (1 - f_limb) + p.skin * (f_limb - f_fat) + p.fat * (f_fat - f_muscle) + p.muscle * f_muscle)
    w_cort = f_bone - f_inner
    w_canal = f_inner * f_canal
    w_trab = f_inner - w_canal
    vol = soft * (1 - f_bone) + cort * w_cort + p.marrow * w_canal + trab * w_trab

    outside = 1 - f_bone
    fractions = np.stack([(1 - f_limb) * outside, (f_limb - f_fat) * outside, (f_fat - f_muscle) * outside,
                          f_muscle * outside, w_canal, w_trab, w_cort])
    tissue = np.argmax(fractions, axis=0).astype(np.int8)
    if return_fractions:
        return vol.astype(np.float32), tissue, fractions.astype(np.float32)
    return vol.astype(np.float32), tissue


@dataclass
class Phantom:
    """A simulated CT of one bone: volume (1/mm), tissue map, bone label and signed distance."""

    volume: np.ndarray
    tissue: np.ndarray
    label: np.ndarray
    sdf: np.ndarray
    grid: object
    params: DensityParams


def make_phantom(vertices, faces, grid, params: DensityParams = DensityParams(), seed: int = 0,
                 vary: bool = True, axis=None) -> Phantom:
    """Closed bone surface (mm) -> CT-like phantom on ``grid``; with ``vary`` the density and
    soft-tissue parameters get the seeded per-subject variation of :func:`vary_params`."""
    grid = as_grid(grid)
    v, f = check_mesh(vertices, faces, closed=True)
    lo, hi = v.min(0), v.max(0)
    g_lo = np.asarray(grid.origin)
    g_hi = g_lo + (np.asarray(grid.shape[::-1]) - 1) * np.asarray(grid.spacing)
    if np.any(lo < g_lo) or np.any(hi > g_hi):
        raise ValueError(f"the surface (x, y, z mm from {np.round(lo, 1)} to {np.round(hi, 1)}) does not fit in "
                         f"the grid ({np.round(g_lo, 1)} to {np.round(g_hi, 1)}): align it to the template "
                         "frame first or use a larger grid")
    label = mesh_to_label(v, f, grid)
    sdf = signed_distance((v, f), grid)
    used = vary_params(params, seed) if vary else params
    vol, tissue = density_volume(label, sdf, grid, used, seed=seed, axis=axis)
    return Phantom(vol, tissue, label, sdf, grid, used)


# --------------------------------------------------------------------------------------- populations
def cache_dir() -> str:
    """Where clgs keeps built models: ``$CLGS_CACHE_DIR``, else ``$XDG_CACHE_HOME/clgs``, else
    ``~/.cache/clgs``."""
    import os

    env = os.environ.get("CLGS_CACHE_DIR")
    if env:
        return os.path.abspath(os.path.expanduser(env))
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(xdg, "clgs")


def scan_geometry_kwargs(grid, DSO: float = 1000.0, DSD: float = 1500.0, pixel_mm: float = 3.0,
                         margin: float = 1.04) -> dict:
    """Geometry keyword arguments (no angles) for a cone-beam scan of ``grid``, centred on the
    rotation axis (offOrigin 0), with a flat detector just large enough to see the whole volume
    from every angle (the nearest corner to the source sets the magnification)."""
    nz, ny, nx = grid.shape
    dx, dy, dz = grid.spacing
    half = 0.5 * np.array([nx * dx, ny * dy, nz * dz])
    r = float(np.hypot(half[0], half[1]))
    if r >= DSO:
        raise ValueError(f"the volume (in-plane half-diagonal {r:.0f} mm) does not fit inside DSO={DSO} mm")
    mag = DSD / (DSO - r)
    u = 2 * margin * DSD * r / np.sqrt(DSO**2 - r**2)
    v = 2 * margin * half[2] * mag
    nu = int(8 * np.ceil(u / pixel_mm / 8))
    nv = int(8 * np.ceil(v / pixel_mm / 8))
    return {"mode": "cone", "DSO": float(DSO), "DSD": float(DSD), "nDetector": [nv, nu],
            "dDetector": [float(pixel_mm), float(pixel_mm)], "nVoxel": [nz, ny, nx], "dVoxel": [dz, dy, dx],
            "offOrigin": [0.0, 0.0, 0.0], "offDetector": [0.0, 0.0]}


class SurfacePopulation:
    """An anatomy made from real closed surfaces in vertex correspondence (one file per subject).

    Generic: a plugin gives the files, the held-out ids, the CT grid, the density parameters and
    the scan settings; this class supplies everything the :class:`clgs.anatomy.Anatomy` contract
    needs (subjects as simulated CTs, the template = vertex-wise mean surface of the population,
    the cached shape model and density atlas, mesh import with rigid alignment).

    Coordinates: the files' frame shifted by ``-frame_offset`` (x, y, z mm), chosen so the CT grid
    is centred on the scanner's rotation axis (Geometry offOrigin = 0)."""

    @classmethod
    def centred(cls, *, shape, spacing_mm: float, pixel_mm: float, n_views: int = 50, arc_deg: float = 180.0,
                DSO: float = 1000.0, DSD: float = 1500.0, **kwargs) -> "SurfacePopulation":
        """A population on a grid of ``shape`` (Z, Y, X) isotropic ``spacing_mm`` voxels centred on the
        rotation axis, scanned in cone beam (DSO/DSD mm) with ``pixel_mm`` detector pixels sized to
        see it whole; ``kwargs`` are the remaining constructor arguments."""
        from clgs.geometry import Grid

        n = np.asarray(shape[::-1])
        grid = Grid(tuple(shape), tuple(-0.5 * (n - 1) * spacing_mm), (float(spacing_mm),) * 3)
        scene = scan_geometry_kwargs(grid, DSO=DSO, DSD=DSD, pixel_mm=pixel_mm)
        scene.update(n_views=n_views, arc_deg=arc_deg)
        return cls(grid=grid, scene=scene, **kwargs)

    def __init__(self, name: str, summary: str, version: str, data_dir, file_pattern: str, ids, test_ids,
                 grid, params: DensityParams, frame_offset, scene: dict, builder_settings: dict | None = None,
                 notice: str = ""):
        self.name = name
        self.summary = summary
        self.version = version
        self.data_dir = str(data_dir)
        self.file_pattern = file_pattern
        self.ids = [str(i) for i in ids]
        self.test_ids = [str(i) for i in test_ids]
        unknown = sorted(set(self.test_ids) - set(self.ids))
        if unknown:
            raise ValueError(f"{name}: held-out ids {unknown} are not among the subjects")
        self.grid = as_grid(grid)
        self.params = params
        self.frame_offset = np.asarray(frame_offset, float)
        self.scene = dict(scene)
        self.builder_settings = dict(builder_settings or {})
        self.notice = notice
        self._template = None
        self._faces = None

    # ---- subjects
    def population(self) -> list:
        """Ids that build the model (every subject except the held-out ones)."""
        return [i for i in self.ids if i not in set(self.test_ids)]

    def test_subjects(self) -> list:
        return list(self.test_ids)

    def _file(self, sid) -> str:
        import os

        sid = str(sid)
        if sid not in self.ids:
            raise KeyError(f"{self.name}: unknown subject {sid!r}; subjects are {', '.join(self.ids)}")
        return os.path.join(self.data_dir, self.file_pattern.format(id=sid))

    def mesh(self, sid):
        """(vertices (V, 3) mm in the anatomy frame, faces (F, 3))."""
        with np.load(self._file(sid), allow_pickle=False) as z:
            v = np.asarray(z["vertices"], np.float64) - self.frame_offset
            f = np.asarray(z["faces"], np.int64)
        return v, f

    def seed(self, sid) -> int:
        """The subject's fixed seed (density variation and texture)."""
        import zlib

        return int(zlib.crc32(f"{self.name}/{sid}".encode()))

    def phantom(self, sid, grid=None) -> Phantom:
        v, f = self.mesh(sid)
        return make_phantom(v, f, grid or self.grid, self.params, seed=self.seed(sid))

    def load_subject(self, sid, grid=None):
        """Subject with its surface (mm) and simulated CT volume (1/mm) on the CT grid."""
        from clgs.shape.template import Subject

        sid = str(sid)
        ph = self.phantom(sid, grid)
        v, f = self.mesh(sid)
        g = ph.grid
        return Subject(sid, v, f, volume=ph.volume, spacing=tuple(g.spacing[::-1]), origin=tuple(g.origin[::-1]),
                       meta={"anatomy": self.name, "seed": self.seed(sid), "held_out": sid in self.test_ids,
                             "energy_kev": ph.params.energy_kev, "cortex_mid_mm": ph.params.cortex_mid_mm,
                             "cortical": ph.params.cortical, "trabecular": ph.params.trabecular})

    # ---- template
    def template_mesh(self):
        """Vertex-wise mean of the population's surfaces (held-out subjects excluded)."""
        ids = self.population()
        vs = []
        faces = None
        for sid in ids:
            v, f = self.mesh(sid)
            if faces is None:
                faces = f
            elif f.shape != faces.shape or not np.array_equal(f, faces):
                raise ValueError(f"{self.name}: subject {sid} has another mesh topology; a vertex-wise mean "
                                 "needs surfaces in vertex correspondence")
            vs.append(v)
        return np.mean(vs, axis=0), faces

    def load_template(self):
        """The template (vertex-wise mean surface of the population) on the CT grid."""
        from clgs.shape.template import Template

        if self._template is None:
            v, f = self.template_mesh()
            label = mesh_to_label(v, f, self.grid)
            sdf = signed_distance((v, f), self.grid)
            g = self.grid
            self._template = Template(label, sdf, v, f, tuple(g.spacing[::-1]), tuple(g.origin[::-1]),
                                      name=self.name, meta={"source": "vertex-wise mean of subjects "
                                                            + ",".join(self.population())})
        return self._template

    # ---- model
    def settings_hash(self) -> str:
        """Hash of everything a built model depends on: data files, ids, grid, density, settings."""
        import hashlib
        import json

        h = hashlib.sha256()
        for sid in self.population():
            with open(self._file(sid), "rb") as fh:
                h.update(fh.read())
        record = {"ids": self.population(), "grid": [list(self.grid.shape), list(self.grid.origin),
                                                     list(self.grid.spacing)],
                  "offset": list(self.frame_offset), "params": repr(self.params),
                  "builder": self.builder_settings, "phantom": PHANTOM_VERSION}
        try:
            from clgs.shape.builder import BUILDER_VERSION

            record["builder_version"] = BUILDER_VERSION
        except ImportError:
            pass
        h.update(json.dumps(record, sort_keys=True).encode())
        return h.hexdigest()[:12]

    @property
    def model_path(self) -> str:
        import os

        return os.path.join(cache_dir(), "models", f"{self.name}-{self.settings_hash()}.npz")

    def build_model(self, out_path=None, force: bool = False, subjects=None, **settings) -> str:
        """Build the shape model and density atlas from the population (held-out subjects never
        enter) with :func:`clgs.shape.builder.build_model`; returns the model file path. An
        up-to-date file (same builder settings) is kept; ``force`` rebuilds it."""
        import os
        import time

        from clgs.shape import builder as model_builder

        out_path = os.fspath(out_path) if out_path is not None else self.model_path
        ids = [str(s) for s in (subjects if subjects is not None else self.population())]
        leaked = sorted(set(ids) & set(self.test_ids))
        if leaked:
            raise ValueError(f"{self.name}: held-out subjects {leaked} must never build the model")
        t0, t0_wall = time.perf_counter(), time.time()
        template = self.load_template()
        # loaders, so that subjects whose registration is cached are never simulated again
        subjects = {sid: (lambda sid=sid: self.load_subject(sid)) for sid in ids}
        assert not set(subjects) & set(self.test_ids)
        kwargs = dict(self.builder_settings)
        kwargs.update(settings)
        kwargs.setdefault("force", force)
        extra = dict(kwargs.pop("extra_meta", None) or {})
        extra.update(anatomy=self.name, held_out=self.test_ids, template="vertex-wise mean of the population",
                     density_params=repr(self.params))
        model_builder.build_model(template, subjects, out_path, extra_meta=extra, **kwargs)
        if os.path.getmtime(out_path) < t0_wall:
            return out_path  # it was up to date
        print(f"{self.name}: built the model from {len(subjects)} subjects in {time.perf_counter() - t0:.1f} s "
              f"-> {out_path}")
        return out_path

    def _ensure_model(self) -> str:
        import os

        path = self.model_path
        if not os.path.exists(path):
            print(f"{self.name}: no model at {path} yet; building it (first use)")
            self.build_model()
        return path

    def load_shape_model(self):
        from clgs.shape.model import load_model

        return load_model(self._ensure_model())[0]

    def load_atlas(self):
        from clgs.shape.model import load_model

        return load_model(self._ensure_model(), need_shape_model=False)[1]

    # ---- user meshes
    def align_mesh(self, vertices, faces, allow_mirror: bool = True):
        """Rigidly align a user's surface (any frame, mm; left or right) to the template:
        returns (vertices, faces in the anatomy frame, Alignment)."""
        tv, _ = self.template_mesh()
        al = align_rigid(vertices, tv, allow_mirror=allow_mirror)
        v, f = al.apply_mesh(vertices, faces)
        return v, f, al

    def subject_from_mesh(self, path, seed: int = 0, align: bool = True, sid: str | None = None, echo=print):
        """A simulated CT subject from a mesh file (STL/PLY/OBJ/npz, mm, either side, any frame),
        rigidly aligned to the template first (the fit is reported through ``echo``; None for
        silence): (Subject, Alignment or None)."""
        import os

        from clgs.shape.template import Subject

        from clgs.io.mesh import load_mesh

        v, f = load_mesh(path)
        check_mesh(v, f, closed=True)
        al = None
        if align:
            v, f, al = self.align_mesh(v, f)
            if echo is not None:
                echo(f"aligned {os.fspath(path)} to the {self.name} template: "
                     f"{'mirrored (other side), ' if al.mirrored else ''}RMS {al.rms_mm:.2f} mm after "
                     f"{al.iterations} ICP iterations\nrotation:\n"
                     + np.array2string(al.rotation, precision=4, suppress_small=True)
                     + "\ntranslation (mm): " + np.array2string(al.translation, precision=2))
        ph = make_phantom(v, f, self.grid, self.params, seed=seed)
        g = ph.grid
        meta = {"anatomy": self.name, "seed": int(seed), "source": os.path.abspath(os.fspath(path))}
        if al is not None:
            meta.update(mirrored=bool(al.mirrored), rms_mm=al.rms_mm, matrix=al.matrix.tolist())
        subj = Subject(sid or os.path.splitext(os.path.basename(os.fspath(path)))[0], v, f, volume=ph.volume,
                       spacing=tuple(g.spacing[::-1]), origin=tuple(g.origin[::-1]), meta=meta)
        return subj, al

    # ---- plugin
    def geometry(self, n_views: int = 50, arc: float = np.pi):
        """The default scan of this anatomy (cone beam over ``arc`` radians)."""
        from clgs.geometry import Geometry

        d = {k: v for k, v in self.scene.items() if k in ("mode", "DSO", "DSD", "nDetector", "dDetector", "nVoxel",
                                                            "dVoxel", "offOrigin", "offDetector")}
        d["angles"] = list(np.linspace(0.0, arc, int(n_views), endpoint=False))
        return Geometry.from_dict(d)

    def anatomy(self, commands=()):
        """The :class:`clgs.anatomy.Anatomy` handed to clgs (loaders stay lazy), with two extra
        attributes: ``subject_from_mesh`` and ``population_model`` (this object)."""
        from clgs.anatomy import Anatomy

        try:
            path = self.model_path
        except OSError:
            path = None
        anatomy = Anatomy(name=self.name, summary=self.summary, version=self.version,
                          load_template=self.load_template, load_shape_model=self.load_shape_model,
                          load_atlas=self.load_atlas, population=self.population,
                          test_subjects=self.test_subjects, load_subject=self.load_subject,
                          build_model=self.build_model, scene=dict(self.scene), commands=list(commands),
                          model_path=path)
        # optional extra used by ``clgs <name> simulate --mesh FILE``: align, then fill with density
        anatomy.subject_from_mesh = self.subject_from_mesh
        anatomy.population_model = self
        return anatomy
