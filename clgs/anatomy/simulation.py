"""Simulated CT scans of an anatomy's subjects: the scanner around a subject's grid, a subject
from a surface file, projections with noise. Library code shared by ``clgs <anatomy> ...`` and
:mod:`clgs.experiment` (numpy and the CT code load when a function runs)."""
from __future__ import annotations

import os
from clgs.errors import InputError

GEOMETRY_KEYS = ("mode", "DSO", "DSD", "nDetector", "dDetector", "offDetector")

__all__ = ["scan_geometry", "subject_from_mesh_file", "simulate_subject", "as_float32"]


def as_float32(x):
    """A torch tensor or array as a float32 NumPy array."""
    import numpy as np

    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, np.float32)


def scan_geometry(anatomy, subject, n_views: int, arc: float, geometry_file=None):
    """The anatomy's default scanner (``scene``) around the subject's CT grid.

    The volume grid is the subject's own (nVoxel, dVoxel, and offOrigin = its centre); source,
    detector and mode come from ``anatomy.scene`` (TIGRE names), or are sized to see the volume
    whole (DSD/DSO = 1500/1000 mm) when the plugin gives none. ``geometry_file``: a geometry JSON
    (TIGRE names or per-view vectors, in the subject's world mm) that replaces the scanner, the
    views and the arc; its volume grid, if any, gives way to the subject's."""
    import numpy as np

    from clgs.geometry import Geometry, read_geometry

    shape = np.asarray(subject.volume.shape)
    spacing = np.asarray(subject.spacing, float)
    centre = np.asarray(subject.origin, float) + 0.5 * (shape - 1) * spacing
    if geometry_file is not None:
        return read_geometry(geometry_file, {"nVoxel": [int(s) for s in shape], "dVoxel": [float(s) for s in spacing],
                                             "offOrigin": [float(c) for c in centre]})
    angles = np.linspace(0.0, arc, int(n_views), endpoint=False)
    scene = dict(anatomy.scene or {})
    d = {k: scene[k] for k in GEOMETRY_KEYS if k in scene}
    d.update(nVoxel=tuple(int(s) for s in shape), dVoxel=tuple(spacing), offOrigin=tuple(centre), angles=angles)
    if "nDetector" not in d or "dDetector" not in d:
        size = float((shape * spacing).max())
        d.setdefault("DSO", 1000.0)
        d.setdefault("DSD", 1500.0)
        mag = d["DSD"] / d["DSO"] if d.get("mode", "cone") == "cone" else 1.0
        half = 0.5 * size * np.sqrt(2.0) * mag * 1.05 + np.linalg.norm(centre[1:]) * mag
        n_det = int(scene.get("n_detector", 256))
        d.update(nDetector=(n_det, n_det), dDetector=(2 * half / n_det,) * 2)
    d.setdefault("DSO", 1000.0)
    d.setdefault("DSD", 1500.0)
    return Geometry(**d)


def subject_from_mesh_file(anatomy, path, seed: int = 0):
    """A Subject (with a CT volume) from a surface file: the plugin's ``subject_from_mesh`` when it
    has one; otherwise the surface filled with a uniform bone attenuation ``scene['density']``
    (1/mm, default 0.04) on a grid of the template's spacing with a 10 mm margin."""
    if getattr(anatomy, "subject_from_mesh", None) is not None:
        out = anatomy.subject_from_mesh(path, seed=seed)
        return out[0] if isinstance(out, tuple) else out
    import numpy as np

    from clgs.io.mesh import load_mesh
    from clgs.shape.template import Subject, box_grid, mesh_to_label

    v, f = load_mesh(path)
    v = np.asarray(v, float)
    spacing = float(min(anatomy.load_template().spacing)) if anatomy.load_template is not None else 2.0
    shape, sp, org = box_grid(v.min(0) - 10.0, v.max(0) + 10.0, spacing=spacing)
    density = float((anatomy.scene or {}).get("density", 0.04))
    vol = mesh_to_label(v, f, shape, sp, org).astype(np.float32) * density
    sid = os.path.splitext(os.path.basename(os.fspath(path)))[0]
    return Subject(sid, v, f, volume=vol, spacing=sp, origin=org,
                   meta={"source": os.path.abspath(os.fspath(path)), "density_model": "uniform", "density": density})


def simulate_subject(anatomy, subject, n_views: int = 50, arc: float = 3.141592653589793, noise: bool = True,
                     seed: int = 0, noise_options: dict = None, protocol: str = "fine", geometry_file=None):
    """Project a subject's CT with the anatomy's scanner, add noise: a :class:`clgs.io.scan.Scan`.
    ``geometry_file``: the scanner and views from a geometry JSON instead (see :func:`scan_geometry`).

    ``protocol`` (see :mod:`clgs.ct.simulation_grid`): ``"fine"`` projects the subject's CT refined
    to a grid twice as fine (no inverse crime), ``"same"`` projects it on its own grid, which is
    also the reconstruction grid (R2-Gaussian's protocol). The truth volume and the true surface
    travel with the scan (for evaluation)."""
    from clgs.ct.simulation_grid import projection_volume
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector

    if subject.volume is None:
        raise InputError(f"subject {subject.id} has no CT volume to simulate")
    geo = scan_geometry(anatomy, subject, n_views, arc, geometry_file)
    source = projection_volume(subject.volume, geo.nVoxel, protocol)
    sim = geo.to_dict()
    sim.update(nVoxel=list(source.shape), dVoxel=[n * d / m for n, d, m in zip(geo.nVoxel, geo.dVoxel, source.shape)])
    proj = as_float32(CTProjector(Geometry.from_dict(sim)).forward(source))
    acquisition = {"noise": bool(noise), "seed": int(seed),
                   "simulation": {"protocol": protocol, "projected_grid": list(source.shape),
                                  "reconstruction_grid": list(geo.nVoxel)}}
    if noise:
        from clgs.ct.noise import add_noise

        opts = dict(noise_options or {})
        proj = as_float32(add_noise(proj, seed=seed, **opts))
        acquisition.update(opts)
    meta = {"anatomy": anatomy.name, "subject": subject.id, "acquisition": acquisition,
            "provenance": f"clgs {anatomy.name} simulate ({anatomy.package or 'plugin'} {anatomy.version})",
            "subject_meta": subject.meta}
    return Scan(geo, proj, truth=subject.volume, meta=meta, surface=(subject.vertices, subject.faces))
