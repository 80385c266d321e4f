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
from clgs.anatomy.alignment import principal_axes
from clgs.errors import InputError
from clgs.io.mesh import check_mesh
from clgs.mesh.voxels import as_grid, grid_axes, mesh_to_label, signed_distance

# version of the phantom model: part of the key of cached models built from phantoms
PHANTOM_VERSION = 2

# tissue codes of the label map returned with every phantom (dominant tissue per voxel)
AIR, SKIN, FAT, MUSCLE, MARROW, TRABECULAR, CORTICAL = range(7)
TISSUE_NAMES = ("air", "skin", "fat", "muscle", "marrow", "trabecular", "cortical")


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
        raise InputError("the label has fewer than 4 voxels: cannot find its long axis")
    xs, ys, zs = grid_axes(grid)
    p = np.stack([xs[ii], ys[jj], zs[kk]], 1)
    c = p.mean(0)
    d = principal_axes(p)[:, 0]
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
        raise InputError("the bone label is empty: nothing to wrap soft tissue around")
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
        raise InputError(f"label {label.shape} and sdf {sdf.shape} must both have the grid's shape {grid.shape}")
    if not np.all(np.isfinite(sdf)):
        raise InputError("the signed distance contains NaN or Inf")
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
        raise InputError(f"the surface (x, y, z mm from {np.round(lo, 1)} to {np.round(hi, 1)}) does not fit in "
                         f"the grid ({np.round(g_lo, 1)} to {np.round(g_hi, 1)}): align it to the template "
                         "frame first or use a larger grid")
    label = mesh_to_label(v, f, grid)
    sdf = signed_distance((v, f), grid)
    used = vary_params(params, seed) if vary else params
    vol, tissue = density_volume(label, sdf, grid, used, seed=seed, axis=axis)
    return Phantom(vol, tissue, label, sdf, grid, used)
