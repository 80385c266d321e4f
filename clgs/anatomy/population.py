"""An anatomy made from a population of real surfaces: subjects as simulated CTs (the tissue
model of :mod:`clgs.anatomy.phantom`), the template, the cached shape model and atlas, and the
scanner that sees the whole grid. What a plugin wraps (see ``anatomies/femur``)."""
from __future__ import annotations

import os

import numpy as np

from clgs.anatomy.alignment import align_rigid
from clgs.anatomy.phantom import PHANTOM_VERSION, DensityParams, Phantom, make_phantom
from clgs.anatomy.record import Anatomy, Scene
from clgs.errors import InputError
from clgs.geometry import DETECTOR_MARGIN, shadow_half_extents
from clgs.io.mesh import check_mesh
from clgs.mesh.voxels import as_grid, mesh_to_label, signed_distance

#: version of :meth:`SurfacePopulation.population_fit`'s record (a new one is computed when it changes)
FIT_VERSION = 1

#: length units a surface file may be in, and their size in mm
UNIT_NAMES = {"millimetres": 1.0, "centimetres": 10.0, "metres": 1000.0, "inches": 25.4}
_UNIT_KEYS = {"mm": "millimetres", "cm": "centimetres", "m": "metres", "in": "inches"}


def unit_key(name: str) -> str:
    return {v: k for k, v in _UNIT_KEYS.items()}[name]


def unit_factor(units: str) -> float:
    """mm per unit of ``units`` ("mm", "cm", "m", "in")."""
    if units not in _UNIT_KEYS:
        raise InputError(f"units {units!r}: give one of {', '.join(_UNIT_KEYS)}")
    return UNIT_NAMES[_UNIT_KEYS[units]]


def surface_length(vertices) -> float:
    """A surface's length (mm) along its longest principal axis: the same in any frame."""
    from clgs.anatomy.alignment import principal_axes

    p = np.asarray(vertices, float)
    return float(np.ptp(p @ principal_axes(p)[:, 0]))


def _limb_reaches_border(tissue) -> bool:
    """Whether anything but air touches the grid's sides across the leg (x and y faces)."""
    return bool(tissue[:, :, 0].any() or tissue[:, :, -1].any() or tissue[:, 0, :].any() or tissue[:, -1, :].any())


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
                         margin: float | None = None) -> dict:
    """Geometry keyword arguments (no angles) for a cone-beam scan of ``grid``, centred on the
    rotation axis (offOrigin 0), with a flat detector just large enough to see the whole volume
    from every angle (the nearest corner to the source sets the magnification), ``margin``
    (default ``clgs.geometry.DETECTOR_MARGIN``) times its shadow."""
    margin = DETECTOR_MARGIN if margin is None else float(margin)
    nz, ny, nx = grid.shape
    dx, dy, dz = grid.spacing
    half_u, half_v = shadow_half_extents((nz * dz, ny * dy, nx * dx), DSO, DSD, "cone")
    u, v = 2 * margin * half_u, 2 * margin * half_v
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
                DSO: float = 1000.0, DSD: float = 1500.0, **kwargs) -> SurfacePopulation:
        """A population on a grid of ``shape`` (Z, Y, X) isotropic ``spacing_mm`` voxels centred on the
        rotation axis, scanned in cone beam (DSO/DSD mm) with ``pixel_mm`` detector pixels sized to
        see it whole; ``kwargs`` are the remaining constructor arguments."""
        from clgs.geometry import Grid

        n = np.asarray(shape[::-1])
        grid = Grid(tuple(shape), tuple(-0.5 * (n - 1) * spacing_mm), (float(spacing_mm),) * 3)
        scene = scan_geometry_kwargs(grid, DSO=DSO, DSD=DSD, pixel_mm=pixel_mm)
        scene.update(n_views=n_views, arc_deg=arc_deg)
        return cls(grid=grid, scene=Scene.from_dict(scene), **kwargs)

    def __init__(self, name: str, summary: str, version: str, data_dir, file_pattern: str, ids, test_ids,
                 grid, params: DensityParams, frame_offset, scene: Scene | dict,
                 builder_settings: dict | None = None,
                 notice: str = "", side_of=None):
        self.name = name
        self.summary = summary
        self.version = version
        self.data_dir = str(data_dir)
        self.file_pattern = file_pattern
        self.ids = [str(i) for i in ids]
        self.test_ids = [str(i) for i in test_ids]
        unknown = sorted(set(self.test_ids) - set(self.ids))
        if unknown:
            raise InputError(f"{name}: held-out ids {unknown} are not among the subjects")
        self.grid = as_grid(grid)
        self.params = params
        self.frame_offset = np.asarray(frame_offset, float)
        self.scene = Scene.from_dict(scene)
        self.builder_settings = dict(builder_settings or {})
        self.notice = notice
        # side_of(vertices) -> (side, measure mm): subjects of the other side than most are mirrored
        # into it (clgs.anatomy.sides); None: every subject as its file has it
        self.side_of = side_of
        self._sides = None
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

    def _file_mesh(self, sid):
        with np.load(self._file(sid), allow_pickle=False) as z:
            v = np.asarray(z["vertices"], np.float64) - self.frame_offset
            f = np.asarray(z["faces"], np.int64)
        return v, f

    def mesh(self, sid):
        """(vertices (V, 3) mm in the anatomy frame, faces (F, 3)), mirrored into the template's
        side when :meth:`sides` says so."""
        v, f = self._file_mesh(sid)
        if self.side_of is not None and self.sides()["subjects"][str(sid)]["mirrored"]:
            from clgs.anatomy.sides import mirror_x

            v, f = mirror_x(v, f)
        return v, f

    def sides(self) -> dict | None:
        """Each subject's side, the template's and who is mirrored
        (:func:`clgs.anatomy.sides.decide_sides`); None without a side test."""
        if self.side_of is None:
            return None
        if self._sides is None:
            from clgs.anatomy.sides import decide_sides

            self._sides = decide_sides({sid: self._file_mesh(sid)[0] for sid in self.ids}, self.side_of,
                                       self.population())
        return self._sides

    def seed(self, sid) -> int:
        """The subject's fixed seed (density variation and texture)."""
        import zlib

        return int(zlib.crc32(f"{self.name}/{sid}".encode()))

    def phantom(self, sid, grid=None) -> Phantom:
        v, f = self.mesh(sid)
        return make_phantom(v, f, grid or self.grid, self.params, seed=self.seed(sid))

    def load_subject(self, sid, grid=None):
        """Subject with its surface (mm) and simulated CT volume (1/mm) on the CT grid."""
        from clgs.progress import phase
        from clgs.shape.template import Subject

        sid = str(sid)
        with phase(f"the CT phantom of {self.name} subject {sid}"):
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
                raise InputError(f"{self.name}: subject {sid} has another mesh topology; a vertex-wise mean "
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
        if self.side_of is not None:
            record["mirrored"] = sorted(s for s, r in self.sides()["subjects"].items() if r["mirrored"])
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
            raise InputError(f"{self.name}: held-out subjects {leaked} must never build the model")
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
        if self.side_of is not None:
            sides = self.sides()
            extra["mirroring"] = dict(sides, subjects={sid: sides["subjects"][sid] for sid in ids})
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
        al = align_rigid(vertices, tv, allow_mirror=allow_mirror, allow_scale=True)
        v, f = al.apply_mesh(vertices, faces)
        return v, f, al

    def _template_length(self) -> float:
        tv, _ = self.template_mesh()
        return surface_length(tv)

    def check_mesh_size(self, vertices, path) -> None:
        """Refuse a surface whose size says wrong units (metres, centimetres, inches) or a different
        object: its longest side must lie within a factor of 3 of the template's. The message names
        the unit that would make it a plausible size (0.6 to 1.5 times the template's length) and
        the ``units`` option (``--units``) that rescales it."""
        length = surface_length(vertices)
        ref = self._template_length()
        if not (ref / 3 <= length <= ref * 3):
            hint = ""
            for unit, factor in UNIT_NAMES.items():
                if factor != 1.0 and 0.6 * ref <= length * factor <= 1.5 * ref:
                    hint = (f"; it looks like {unit}: scale it by {factor:g} to millimetres, or give "
                            f"--units {unit_key(unit)} (units={unit_key(unit)!r} in Python)")
            raise InputError(f"{os.fspath(path)}: the surface is {length:.4g} units long, a {self.name} of this "
                             f"population about {ref:.0f} mm{hint}")

    def population_fit(self) -> dict:
        """How the population's own surfaces fit the template, measured as a user's surface is
        (:func:`align_rigid` with scale): ``shape_rms_mm`` per subject and the range of lengths.
        Kept in the cache folder beside the model (about 20 s to compute)."""
        import json

        path = os.path.join(cache_dir(), "models", f"{self.name}-{self.settings_hash()}-fit{FIT_VERSION}.json")
        if os.path.isfile(path):
            try:
                with open(path) as fh:
                    return json.load(fh)
            except (OSError, ValueError):
                pass
        tv, _ = self.template_mesh()
        rms, lengths = {}, {}
        for sid in self.population():
            v, _ = self.mesh(sid)
            rms[sid] = align_rigid(v, tv, allow_mirror=False, allow_scale=True).shape_rms_mm
            lengths[sid] = surface_length(v)
        out = {"shape_rms_mm": rms, "length_mm": lengths}
        try:
            from clgs.io import atomic

            os.makedirs(os.path.dirname(path), exist_ok=True)
            atomic.write_json(path, out)
        except OSError:
            pass
        return out

    def plausible_rms_mm(self) -> float:
        """The shape residual (alignment RMS with the size set aside) beyond which a surface is
        unlike this population's: twice the worst of the population's own (LLP26 femurs: 2.2-4 mm;
        a box of a femur's size: about 80 mm)."""
        return 2.0 * max(self.population_fit()["shape_rms_mm"].values())

    def subject_grid(self, vertices, xy_margin_mm: float = 45.0, z_margin_mm: float = 10.0):
        """The CT grid of a subject: the template's grid, grown by whole voxels on both sides (its
        voxel centres stay on the template's lattice and its centre on the rotation axis) until it
        holds the surface with ``z_margin_mm`` along the leg and ``xy_margin_mm`` across it (room
        for the limb)."""
        from clgs.geometry import Grid

        g = self.grid
        sp = np.asarray(g.spacing, float)  # (x, y, z)
        n = np.asarray(g.shape[::-1])  # (x, y, z)
        half = 0.5 * (n - 1) * sp
        centre = np.asarray(g.origin, float) + half
        v = np.asarray(vertices, float) - centre
        need = np.max(np.abs(v), axis=0) + np.array([xy_margin_mm, xy_margin_mm, z_margin_mm])
        grow = np.maximum(0, np.ceil((need - half) / sp)).astype(int)
        n2 = n + 2 * grow
        return Grid(tuple(int(x) for x in n2[::-1]), tuple(centre - 0.5 * (n2 - 1) * sp), tuple(sp))

    def subject_from_mesh(self, path, seed: int = 0, align: bool = True, sid: str | None = None, echo=print,
                          units: str = "mm", space: str | None = None):
        """A simulated CT subject from a mesh file (STL/PLY/OBJ/npz, either side, any frame),
        rigidly aligned to the template first (the fit is reported through ``echo``; None for
        silence): (Subject, Alignment or None).

        ``units``: the file's length unit ("mm", "cm", "m", "in"); a size that says another unit
        than the one given is refused (:meth:`check_mesh_size`). The CT grid follows the subject
        (:meth:`subject_grid`): any length is simulated with its own size, while the shape model and
        atlas stay on the template's grid. A surface whose shape (size set aside) fits the template
        far worse than the population's own is warned about, with both numbers, before the CT is
        made. ``space``: the frame ("RAS" or "LPS") of a surface file that declares none
        (:func:`clgs.io.mesh.load_mesh`)."""
        import os

        from clgs.io.mesh import load_mesh
        from clgs.shape.template import Subject

        factor = unit_factor(units)
        v, f = load_mesh(path, space=space)
        v = np.asarray(v, float) * factor
        check_mesh(v, f, closed=True)
        self.check_mesh_size(v, path)
        al = None
        if align:
            v, f, al = self.align_mesh(v, f)
            fit = self.population_fit()
            limit = self.plausible_rms_mm()
            worst = max(fit["shape_rms_mm"].values())
            if al.shape_rms_mm > limit:
                import warnings

                warnings.warn(f"{os.fspath(path)} fits the {self.name} template poorly: its shape is "
                              f"{al.shape_rms_mm:.1f} mm RMS from the template after alignment (size set aside), "
                              f"where this population's {self.name}s lie within {worst:.1f} mm (warned beyond "
                              f"{limit:.1f} mm); it may not be a {self.name} (its simulated CT and any prior "
                              "will be wrong)", stacklevel=2)
            if echo is not None:
                lengths = list(fit["length_mm"].values())
                length = surface_length(v)
                side = " (beyond the population's lengths: the shape model extrapolates)" if not (
                    min(lengths) <= length <= max(lengths)) else ""
                echo(f"aligned {os.fspath(path)} to the {self.name} template: "
                     f"{'mirrored (other side), ' if al.mirrored else ''}RMS {al.rms_mm:.2f} mm after "
                     f"{al.iterations} ICP iterations; shape {al.shape_rms_mm:.2f} mm RMS at the template's size "
                     f"(population: up to {worst:.2f} mm); length {length:.0f} mm, {1.0 / al.scale:.3f} x the "
                     f"template's (population: {min(lengths):.0f}-{max(lengths):.0f} mm){side}\nrotation:\n"
                     + np.array2string(al.rotation, precision=4, suppress_small=True)
                     + "\ntranslation (mm): " + np.array2string(al.translation, precision=2))
        grid = self.subject_grid(v)
        for attempt in range(1, 5):  # grown until the limb has air around it
            ph = make_phantom(v, f, grid, self.params, seed=seed)
            if not _limb_reaches_border(ph.tissue):
                break
            grid = self.subject_grid(v, xy_margin_mm=45.0 + 30.0 * attempt)
        g = ph.grid
        meta = {"anatomy": self.name, "seed": int(seed), "source": os.path.abspath(os.fspath(path)),
                "units": units, "unit_factor": factor,
                "grid": {"shape_zyx": list(g.shape), "origin_xyz": list(g.origin), "spacing_xyz": list(g.spacing)},
                "template_grid": tuple(g.shape) == tuple(self.grid.shape)}
        if al is not None:
            meta.update(mirrored=bool(al.mirrored), rms_mm=al.rms_mm, matrix=al.matrix.tolist(),
                        shape_rms_mm=al.shape_rms_mm, size_vs_template=1.0 / al.scale,
                        length_mm=surface_length(v))
        subj = Subject(sid or os.path.splitext(os.path.basename(os.fspath(path)))[0], v, f, volume=ph.volume,
                       spacing=tuple(g.spacing[::-1]), origin=tuple(g.origin[::-1]), meta=meta)
        return subj, al

    # ---- plugin
    def geometry(self, n_views: int = 50, arc: float = np.pi):
        """The default scan of this anatomy (cone beam over ``arc`` radians)."""
        from clgs.geometry import Geometry

        d = self.scene.geometry_settings()
        d["angles"] = list(np.linspace(0.0, arc, int(n_views), endpoint=False))
        return Geometry.from_dict(d)

    def anatomy(self) -> Anatomy:
        """The :class:`clgs.anatomy.Anatomy` handed to clgs (loaders stay lazy), with
        ``subject_from_mesh`` (``clgs <name> simulate --mesh FILE``: align, then simulate) and
        ``population_model`` (this object)."""
        try:
            path = self.model_path
        except OSError:
            path = None
        return Anatomy(name=self.name, summary=self.summary, version=self.version,
                       load_template=self.load_template, load_shape_model=self.load_shape_model,
                       load_atlas=self.load_atlas, population=self.population,
                       test_subjects=self.test_subjects, load_subject=self.load_subject,
                       build_model=self.build_model, scene=self.scene, model_path=path,
                       subject_from_mesh=self.subject_from_mesh, population_model=self)

