"""Simulated CT scans of an anatomy's subjects: the scanner around a subject's grid, a subject
from a surface file, projections with noise. Library code shared by ``clgs <anatomy> ...`` and
:mod:`clgs.experiment` (numpy and the CT code load when a function runs)."""
from __future__ import annotations

import os

from clgs.anatomy.record import Scene
from clgs.errors import InputError

GEOMETRY_KEYS = ("mode", "DSO", "DSD", "nDetector", "dDetector", "offDetector")

__all__ = ["scan_geometry", "subject_from_mesh_file", "simulate_subject", "as_float32"]


def as_float32(x):
    """A torch tensor or array as a float32 NumPy array."""
    import numpy as np

    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, np.float32)


def _detector_sized(shape, spacing, centre, d: dict, n_det: int):
    """(nDetector, dDetector) of a flat detector that sees a grid (Z, Y, X shape and spacing, centre
    (Z, Y, X) mm) whole from every angle, ``clgs.geometry.DETECTOR_MARGIN`` larger than its
    shadow; the pixel is ``d['dDetector']`` when given."""
    import numpy as np

    from clgs.geometry import DETECTOR_MARGIN, shadow_half_extents

    size = np.asarray(shape) * np.asarray(spacing, float)
    size = size + 2.0 * np.abs(np.asarray(centre, float))  # a box about the axis that holds the grid
    half_u, half_v = shadow_half_extents(tuple(size), d["DSO"], d["DSD"], d.get("mode", "cone"))
    if "dDetector" in d:
        pix = np.asarray(d["dDetector"], float)
    else:
        pix = np.full(2, 2 * DETECTOR_MARGIN * max(half_u, half_v) / n_det)
    nv = int(8 * np.ceil(2 * DETECTOR_MARGIN * half_v / pix[0] / 8))
    nu = int(8 * np.ceil(2 * DETECTOR_MARGIN * half_u / pix[1] / 8))
    return (nv, nu), (float(pix[0]), float(pix[1]))


def scan_geometry(anatomy, subject, n_views: int, arc: float, angles=None, detector_mm=None, geometry_file=None):
    """The anatomy's default scanner (``scene``) around the subject's CT grid.

    The volume grid is the subject's own (nVoxel, dVoxel, and offOrigin = its centre); source,
    detector and mode come from ``anatomy.scene`` (TIGRE names). The scene's detector is used as
    it is for the grid it was sized for (its ``nVoxel``; a scene without one keeps its detector for
    any subject); a subject on another grid (a longer bone) gets a detector of the same pixels
    sized to see its grid whole, and so does a plugin that gives no detector (DSD/DSO = 1500/1000
    mm).

    ``angles`` (radians): the views, instead of ``n_views`` spread over ``arc`` (end excluded).
    ``detector_mm`` (V, U): the field of view at the isocentre of a smaller detector (a C-arm's),
    centred; the detector is that times the magnification DSD/DSO, in the same pixels. A bone
    larger than it is seen truncated.

    ``geometry_file``: a geometry JSON (TIGRE names or per-view vectors, in the subject's world mm)
    that replaces the scanner, the views and the arc; its volume grid, if any, gives way to the
    subject's."""
    import numpy as np

    from clgs.errors import InputError
    from clgs.geometry import Geometry, read_geometry

    shape = np.asarray(subject.volume.shape)
    spacing = np.asarray(subject.spacing, float)
    centre = np.asarray(subject.origin, float) + 0.5 * (shape - 1) * spacing
    if geometry_file is not None:
        if angles is not None or detector_mm is not None:
            raise InputError("a geometry file gives the views and the detector: leave out angles and detector_mm")
        return read_geometry(geometry_file, {"nVoxel": [int(s) for s in shape], "dVoxel": [float(s) for s in spacing],
                                             "offOrigin": [float(c) for c in centre]})
    if angles is None:
        angles = np.linspace(0.0, arc, int(n_views), endpoint=False)
    angles = np.asarray(angles, float).reshape(-1)
    if angles.size == 0 or not np.all(np.isfinite(angles)):
        raise InputError(f"angles must be one or more finite numbers, got {angles!r}")
    scene = Scene.from_dict(anatomy.scene)
    d = {k: scene[k] for k in GEOMETRY_KEYS if k in scene}
    d.setdefault("DSO", 1000.0)
    d.setdefault("DSD", 1500.0)
    # the scene's detector was sized for its grid (nVoxel); a scene that names no grid keeps its
    # detector whatever the subject's
    own_grid = scene.nVoxel is None or (
        tuple(scene.nVoxel) == tuple(int(s) for s in shape)
        and np.allclose(scene.get("dVoxel", spacing), spacing) and np.allclose(scene.get("offOrigin", centre), centre))
    if "nDetector" not in d or "dDetector" not in d or not own_grid:
        d["nDetector"], d["dDetector"] = _detector_sized(shape, spacing, centre, d, scene.get("n_detector", 256))
        d["offDetector"] = (0.0, 0.0)
    if detector_mm is not None:
        fov = np.asarray(detector_mm, float).reshape(-1)
        fov = np.repeat(fov, 2) if fov.size == 1 else fov
        if fov.size != 2 or not np.all(np.isfinite(fov)) or np.any(fov <= 0):
            raise InputError(f"detector size {detector_mm!r}: give one or two positive numbers (mm at the "
                             "isocentre, V then U)")
        mag = d["DSD"] / d["DSO"] if d.get("mode", "cone") == "cone" else 1.0
        pix = np.asarray(d["dDetector"], float)
        n = np.maximum(1, np.round(fov * mag / pix)).astype(int)
        d["nDetector"] = (int(n[0]), int(n[1]))
    d.update(nVoxel=tuple(int(s) for s in shape), dVoxel=tuple(spacing), offOrigin=tuple(centre), angles=angles)
    return Geometry(**d)


def subject_from_mesh_file(anatomy, path, seed: int = 0, units: str = "mm", space: str | None = None):
    """A Subject (with a CT volume) from a surface file: the plugin's ``subject_from_mesh`` when it
    has one; otherwise the surface filled with a uniform bone attenuation ``scene.density``
    (1/mm, default 0.04) on a grid of the template's spacing with a 10 mm margin. ``units``: the
    file's length unit ("mm", "cm", "m", "in"), rescaled to mm; ``space``: the frame ("RAS" or
    "LPS") of a file that declares none (default LPS, with a warning: :func:`clgs.io.mesh.load_mesh`)."""
    import inspect

    from clgs.anatomy.population import unit_factor

    factor = unit_factor(units)
    if getattr(anatomy, "subject_from_mesh", None) is not None:
        params = inspect.signature(anatomy.subject_from_mesh).parameters
        if space is not None and "space" not in params:
            raise InputError(f"the {anatomy.name} plugin reads surface files in its own frame: leave out the frame "
                             f"({space}) given for {path}")
        extra = {"space": space} if "space" in params else {}
        if "units" in params:
            out = anatomy.subject_from_mesh(path, seed=seed, units=units, **extra)
        elif units != "mm":
            raise InputError(f"the {anatomy.name} plugin reads surfaces in mm only: scale {path} by {factor:g}")
        else:
            out = anatomy.subject_from_mesh(path, seed=seed, **extra)
        return out[0] if isinstance(out, tuple) else out
    import numpy as np

    from clgs.io.mesh import load_mesh
    from clgs.shape.template import Subject, box_grid, mesh_to_label

    v, f = load_mesh(path, space=space)
    v = np.asarray(v, float) * factor
    spacing = float(min(anatomy.load_template().spacing)) if anatomy.load_template is not None else 2.0
    shape, sp, org = box_grid(v.min(0) - 10.0, v.max(0) + 10.0, spacing=spacing)
    density = Scene.from_dict(anatomy.scene).get("density", 0.04)
    vol = mesh_to_label(v, f, shape, sp, org).astype(np.float32) * density
    sid = os.path.splitext(os.path.basename(os.fspath(path)))[0]
    return Subject(sid, v, f, volume=vol, spacing=sp, origin=org,
                   meta={"source": os.path.abspath(os.fspath(path)), "density_model": "uniform", "density": density})


def simulate_subject(anatomy, subject, n_views: int = 50, arc: float = 3.141592653589793, noise: bool = True,
                     seed: int = 0, noise_options: dict = None, protocol: str = "fine", geometry_file=None,
                     angles=None, detector_mm=None):
    """Project a subject's CT with the anatomy's scanner, add noise: a :class:`clgs.io.scan.Scan`.

    ``protocol`` (see :mod:`clgs.ct.simulation_grid`): ``"fine"`` projects the subject's CT refined
    to a grid twice as fine (no inverse crime), ``"same"`` projects it on its own grid, which is
    also the reconstruction grid (R2-Gaussian's protocol). ``geometry_file``, ``angles`` (radians)
    and ``detector_mm``: see :func:`scan_geometry`. The truth volume and the true surface travel
    with the scan (for evaluation)."""
    import numpy as np

    from clgs.ct.simulate import project_with_noise
    from clgs.io.scan import Scan
    from clgs.progress import phase

    if subject.volume is None:
        raise InputError(f"subject {subject.id} has no CT volume to simulate")
    geo = scan_geometry(anatomy, subject, n_views, arc, angles=angles, detector_mm=detector_mm,
                        geometry_file=geometry_file)
    opts = dict(noise_options or {})
    unknown = set(opts) - {"I0", "sigma", "scatter"}
    if unknown:
        raise InputError(f"noise options {sorted(unknown)} are not I0, sigma or scatter")
    # the anatomy protocol keeps negative line integrals (counts above the flat field) as drawn
    with phase(f"simulating {geo.n_views} views of subject {subject.id}"):
        proj, acquisition = project_with_noise(subject.volume, geo, protocol=protocol, noise=noise, seed=seed,
                                               clamp_negative=False, progress=False, **opts)
    if detector_mm is not None:
        acquisition["detector_fov_mm"] = [float(x) for x in np.broadcast_to(np.asarray(detector_mm, float), (2,))]
    meta = {"anatomy": anatomy.name, "subject": subject.id, "acquisition": acquisition,
            "provenance": f"clgs {anatomy.name} simulate ({anatomy.package or 'plugin'} {anatomy.version})",
            "subject_meta": subject.meta}
    return Scan(geo, proj, truth=subject.volume, meta=meta, surface=(subject.vertices, subject.faces))
