"""One way to simulate a scan: a volume of attenuation (1/mm, or Hounsfield units at an energy) on
a scanner, projected from a finer grid than the reconstruction's (no inverse crime), with TIGRE's
noise model, as a :class:`clgs.io.scan.Scan` whose truth is the volume on the reconstruction grid.

``clgs simulate`` is this function behind a command line; the anatomy commands project their
subjects with :func:`project_with_noise`, the same projection and noise.
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Callable

import numpy as np

from clgs.errors import InputError
from clgs.geometry import DETECTOR_MARGIN, Geometry, shadow_half_extents

__all__ = ["SimulationWarning", "simulate_scan", "project_with_noise", "scanner_geometry"]


class SimulationWarning(UserWarning):
    """Something about a simulated scan a user should know (saturated pixels, a volume thinner
    than a detector row)."""


def _warner(warn: Callable[[str], None] | None) -> Callable[[str], None]:
    if warn is not None:
        return warn
    return lambda message: warnings.warn(message, SimulationWarning, stacklevel=3)


def scanner_geometry(shape, spacing, views: int, arc_deg: float = 180.0, mode: str = "cone", DSD=None, DSO=None,
                     detector: int = 256, pixel=None, centre_xyz=(0.0, 0.0, 0.0)) -> Geometry:
    """A circular scanner turning about the volume's centre (``centre_xyz``, world mm) whose square
    detector of ``detector`` pixels sees the whole volume (``shape`` (Z, Y, X) voxels of ``spacing``
    mm) from every angle, with ``clgs.geometry.DETECTOR_MARGIN``, unless ``pixel`` (mm) is given. DSO / DSD default to
    1000 / 1500 mm. Raises :class:`clgs.geometry.GeometryError` for a source inside the volume."""
    base = Geometry.default(n_views=views, arc=math.radians(arc_deg), mode=mode, n_voxel=max(shape),
                            n_detector=detector, volume_mm=float(max(np.multiply(shape, spacing))))
    DSO = base.DSO if DSO is None else DSO
    DSD = base.DSD if DSD is None else DSD
    half_u, half_v = shadow_half_extents(np.multiply(shape, spacing), DSO, DSD, mode)
    if pixel is None:
        pixel = 2.0 * max(half_u, half_v) * DETECTOR_MARGIN / detector
    d = base.to_dict()
    d.update(DSD=DSD, DSO=DSO, nVoxel=list(shape), dVoxel=list(spacing), dDetector=[pixel, pixel],
             nDetector=[detector, detector], isocentre=[float(c) for c in np.asarray(centre_xyz, float)[::-1]])
    return Geometry.from_dict(d)


def project_with_noise(volume, geometry: Geometry, *, protocol: str = "fine", noise: bool = True,
                       I0: float = 1e5, sigma: float = 10.0, scatter: float = 0.0, seed: int = 0,
                       clamp_negative: bool = True, progress: bool = True,
                       warn: Callable[[str], None] | None = None, announce: Callable | None = None) -> tuple:
    """(projections float32 (views, V, U), acquisition record) of ``volume`` ((Z, Y, X) 1/mm on any
    grid over ``geometry``'s field of view) seen by ``geometry``.

    ``protocol``: ``"fine"`` projects the volume resampled at least twice as fine as the
    reconstruction grid (``geometry.nVoxel``), ``"same"`` projects it on that grid (R2-Gaussian's
    protocol; see :mod:`clgs.ct.simulation_grid`). Noise as :func:`clgs.ct.noise.add_noise`;
    the record counts pixels that fell to the one-count floor (``saturated``, warned about above
    1 %) and, with ``clamp_negative``, line integrals below 0 set to 0 (counts above the flat field,
    as R2-Gaussian's generator clamps them). ``announce(geometry, shape)`` is called before the
    projection with the shape of the volume projected."""
    from clgs.ct.simulation_grid import projection_volume
    from clgs.ops.ct_projector import CTProjector
    from clgs.progress import progress_bar

    warn = _warner(warn)
    views = geometry.n_views
    source = projection_volume(np.asarray(volume, np.float32), tuple(geometry.nVoxel), protocol)
    extent = np.multiply(geometry.nVoxel, geometry.dVoxel)
    sim = geometry.to_dict()
    sim.update(nVoxel=list(source.shape), dVoxel=[float(e) / n for e, n in zip(extent, source.shape)])
    projector = CTProjector(type(geometry).from_dict(sim))
    source = np.ascontiguousarray(source, np.float32)
    if announce is not None:
        announce(geometry, source.shape)
    step = max(1, -(-views // 20))
    parts = []
    quiet = None if progress else True
    with progress_bar(total=views, desc="simulate", unit="view", leave=False, disable=quiet) as bar:
        for first in range(0, views, step):
            chunk = list(range(first, min(first + step, views)))
            parts.append(np.asarray(projector.forward(source, views=chunk), np.float32))
            bar.update(len(chunk))
    proj = np.concatenate(parts, axis=0)
    if not np.all(np.isfinite(proj)):
        raise InputError(
            f"the line integrals overflow 32-bit floats (attenuation up to {float(np.max(volume)):.3g} 1/mm over "
            f"paths of up to {float(max(extent)):.0f} mm); attenuation is in 1/mm (bone about 0.05): check the "
            "volume's units")
    if not float(proj.max()) > 0:
        # nothing in the field of view attenuates: a reconstruction of this scan can only find the noise
        warn(f"no ray crosses any attenuation (the volume's largest value in the field of view is "
             f"{float(np.max(source)):.3g} 1/mm): every line integral is 0, so the scan holds "
             f"{'nothing but noise' if noise else 'nothing'}; check the volume's values and units (1/mm, or "
             "--hu for Hounsfield units) and that it lies inside the scanner's field of view")
    acquisition = {"noise": bool(noise), "seed": int(seed),
                   "simulation": {"protocol": protocol, "projected_grid": list(source.shape),
                                  "reconstruction_grid": list(geometry.nVoxel)}}
    if noise:
        from clgs.ct.noise import add_noise

        acquisition.update(I0=I0, sigma=sigma, scatter=scatter)
        max_p = float(proj.max()) if float(proj.max()) > 0 else 1.0  # add_noise's normalisation
        proj = np.asarray(add_noise(proj, I0=I0, sigma=sigma, scatter=scatter, seed=seed), np.float32)
        # a pixel whose count fell to the floor of 1 photon reads log(I0) * max_p: saturated
        saturated = int((proj >= np.float32(math.log(I0) * max_p) * np.float32(1 - 1e-5)).sum())
        acquisition["saturated"] = saturated
        if saturated > 0.01 * proj.size:
            warn(f"{100.0 * saturated / proj.size:.1f} % of the detector pixels fell to the floor of 1 photon count "
                 f"(at --I0 {I0:g} with --sigma {sigma:g}): their line integrals saturate and carry no "
                 "information; raise --I0")
    if clamp_negative:
        neg = proj < 0
        acquisition["clamped_negative"] = int(neg.sum())
        proj[neg] = 0.0
    return proj, acquisition


def _thinner_than_a_row(name, shape, spacing, geometry: Geometry) -> str | None:
    """A volume less than one detector row high (at the rotation axis) projects between rows and
    mostly vanishes from the scan: the message saying so, or None."""
    height = shape[0] * float(spacing[0])
    row = float(np.max(np.linalg.norm(geometry.view_vectors(scene=False)[:, 9:12], axis=1)
                       / geometry.magnification()))
    if height >= row:
        return None
    return (f"{name} is {height:.3g} mm high, less than one detector row at the rotation axis ({row:.3g} mm): its "
            "projection falls between rows and mostly vanishes; use a smaller --pixel, more --detector pixels, or "
            "a thicker volume")


def simulate_scan(volume, spacing=None, origin=None, *, orientation: str | None = None, hu: bool = False,
                  kev: float = 70.0, views: int = 50, arc_deg: float = 180.0, mode: str = "cone", DSO=None, DSD=None,
                  detector: int = 256, pixel=None, geometry=None, grid=None, grid_spacing=None,
                  protocol: str = "fine", noise: bool = True, I0: float = 1e5, sigma: float = 10.0,
                  scatter: float = 0.0, seed: int = 0, surface_level=None, progress: bool = True,
                  name: str = "the volume", warn: Callable[[str], None] | None = None,
                  announce: Callable | None = None, meta: dict | None = None):
    """Simulate a sparse-view scan of ``volume``: a :class:`clgs.io.scan.Scan` (projections,
    geometry, the truth on the reconstruction grid, the acquisition in ``meta``).

    ``volume``: a (Z, Y, X) array (``spacing`` (dZ, dY, dX) mm needed; ``origin`` (x, y, z) mm of
    voxel [0, 0, 0], default centred on 0) or a file :func:`clgs.io.volume.load_volume` reads (its
    own spacing, origin and orientation). Attenuation in 1/mm, or Hounsfield units with ``hu`` at
    ``kev``. The scanner turns about the volume's centre: ``views`` over ``arc_deg`` degrees,
    ``mode``, ``DSO``/``DSD`` (mm), a square ``detector`` of ``pixel`` mm (default: it sees the
    whole volume); or ``geometry`` (a :class:`Geometry`, or a geometry JSON file, TIGRE names or
    per-view vectors, in the scanner's frame; the volume is centred at its ``offOrigin``).
    ``grid`` (N or (NZ, NY, NX)) or ``grid_spacing`` (mm): the reconstruction grid over the same
    field of view (default the volume's own). ``protocol``: ``"fine"`` (the honest default) or
    ``"same"``. Noise: ``I0`` (TIGRE's normalisation: the most attenuating ray keeps ``I0 / e``
    counts), ``sigma`` (counts), ``scatter`` (fraction), ``seed``; ``noise=False`` for clean line
    integrals. ``surface_level`` (1/mm): also keep the truth's iso-surface. Warnings go to
    ``warn`` (a callable taking the message) or Python's warnings; ``announce``: see
    :func:`project_with_noise`. ``orientation`` (nibabel axis
    codes, e.g. ``"LAS"``): the order outputs are written in (a file's own by default)."""
    from clgs.ct.simulation_grid import parse_grid, resample_box
    from clgs.io.scan import Scan

    warn = _warner(warn)
    if isinstance(volume, (str, bytes)) or hasattr(volume, "__fspath__"):
        from clgs.io.volume import load_volume

        name = str(volume) if name == "the volume" else name
        loaded = load_volume(volume)
        vol = np.asarray(loaded.volume, np.float32)
        spacing = loaded.spacing if spacing is None else spacing
        origin = loaded.origin if origin is None else origin
        orientation = orientation or loaded.orientation
    else:
        vol = np.asarray(volume)
        if vol.ndim != 3 or not np.issubdtype(vol.dtype, np.number) or np.iscomplexobj(vol):
            raise InputError(f"{name}: a volume is a 3-D array of real numbers, got shape {vol.shape}, "
                             f"dtype {vol.dtype}")
        vol = vol.astype(np.float32)
    if spacing is None:
        raise InputError(f"{name}: an array without voxel size; give spacing (mm, a number or (dZ, dY, dX))")
    sp = tuple(float(s) for s in np.broadcast_to(np.asarray(spacing, float), (3,)))
    if not all(np.isfinite(sp)) or min(sp) <= 0:
        raise InputError(f"{name}: spacing must be positive numbers of mm, got {spacing!r}")
    if not np.all(np.isfinite(vol)):
        raise InputError(f"{name}: the volume contains NaN or Inf")
    if grid is not None and grid_spacing is not None:
        raise InputError("give a reconstruction grid (voxels) or a grid spacing (mm), not both")
    extent = np.multiply(vol.shape, sp)  # (Z, Y, X) mm: the field of view both grids cover
    recon_shape = parse_grid(grid) if isinstance(grid, str) else (
        None if grid is None else tuple(int(n) for n in np.broadcast_to(np.asarray(grid), (3,))))
    if grid_spacing is not None:
        gsp = np.broadcast_to(np.asarray(grid_spacing, float), (3,))
        recon_shape = tuple(max(1, int(round(float(e) / float(d)))) for e, d in zip(extent, gsp))
    recon_shape = tuple(vol.shape) if recon_shape is None else recon_shape
    recon_sp = tuple(float(e) / n for e, n in zip(extent, recon_shape))
    # the world point the scanner turns about: the input's centre (0 for a bare array)
    centre_xyz = np.zeros(3)
    if origin is not None:
        centre_xyz = np.asarray(origin, float) + 0.5 * (np.asarray(vol.shape[::-1]) - 1) * np.asarray(sp[::-1], float)
    if hu:
        from clgs.io.units import hu_to_mu

        vol = hu_to_mu(vol, kev)
    if float(vol.min()) < 0:
        raise InputError(f"{name}: negative values (min {float(vol.min()):.4g}); simulate expects attenuation "
                         "(1/mm, >= 0); for Hounsfield units (a CT) add --hu (and --kev for the energy)")
    if geometry is not None:
        from clgs.geometry import read_geometry

        geo = geometry if isinstance(geometry, Geometry) else read_geometry(
            geometry, {"nVoxel": list(recon_shape), "dVoxel": list(recon_sp)})
        d = {**geo.to_dict(), "nVoxel": list(recon_shape), "dVoxel": list(recon_sp)}
        # the volume stays where the input lay: its centre is the file's offOrigin in the scanner's frame
        iso = centre_xyz - np.asarray(geo.offOrigin[::-1], float)
        geo = Geometry.from_dict({**d, "isocentre": [float(c) for c in iso[::-1]]})
    else:
        geo = scanner_geometry(recon_shape, recon_sp, views, arc_deg, mode, DSD, DSO, detector, pixel, centre_xyz)
    if orientation:  # outputs keep the input's array order (truth, reconstructions): the geometry carries it
        geo = Geometry.from_dict({**geo.to_dict(), "orientation": orientation})
    thin = _thinner_than_a_row(name, vol.shape, sp, geo)
    if thin:
        warn(thin)
    truth = resample_box(vol, recon_shape)
    proj, acquisition = project_with_noise(vol, geo, protocol=protocol, noise=noise, I0=I0, sigma=sigma,
                                           scatter=scatter, seed=seed, progress=progress, warn=warn,
                                           announce=announce)
    if not noise:  # the settings a noisy re-run would take, kept as the command line records them
        acquisition.update(I0=I0, sigma=sigma, scatter=scatter)
    if hu:
        acquisition["kev"] = float(kev)  # the energy the input's HU were converted at: `reconstruct --to-hu` reads it
    meta = dict(meta or {})
    meta["acquisition"] = {**acquisition, **meta.get("acquisition", {})}
    surface = None
    if surface_level is not None:
        from clgs.mesh.surface import surface_from_volume

        meta["truth_surface_level"] = float(surface_level)
        surface = surface_from_volume(truth, surface_level, geometry=geo)
    return Scan(geo, proj, truth, meta, surface)
