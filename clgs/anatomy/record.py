"""What an anatomy plugin hands to clgs: the typed :class:`Anatomy` record, its default
:class:`Scene` (scanner and surface settings, checked when made) and :class:`AnatomyParts`
(template, shape model, atlas: what a shape-guided reconstruction uses).

Loaders are plain callables so that listing plugins (``clgs --help``, ``clgs anatomies``) never
reads a model from disk; their signatures are the named types below (checked as "callable or
None" when the record is made; the signatures are for readers and type checkers). Every file a
loader reads is data (npz with ``allow_pickle=False``, JSON), never code. This module imports
nothing heavy: the types it names are imported only for type checkers.
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, Optional, Protocol

from clgs.errors import InputError

if TYPE_CHECKING:  # only for type checkers: the records stay light to import
    from clgs.shape.model import DensityAtlas, ShapeModel
    from clgs.shape.template import Subject, Template

__all__ = ["Anatomy", "AnatomyParts", "Scene", "SceneError", "AnatomyError", "TemplateLoader", "ShapeModelLoader",
           "AtlasLoader", "SubjectIds", "SubjectLoader", "ModelBuilder", "SubjectFromMesh"]

#: () -> the template (label, signed distance, surface mesh, grid in mm)
TemplateLoader = Callable[[], "Template"]
#: () -> the shape model, or None when the plugin has none yet
ShapeModelLoader = Callable[[], Optional["ShapeModel"]]
#: () -> the density atlas (mean and variance on the template grid), or None
AtlasLoader = Callable[[], Optional["DensityAtlas"]]
#: () -> subject ids (the model's population, or the held-out ones)
SubjectIds = Callable[[], "list[str]"]
#: (subject id) -> the Subject (surface mesh and CT-like volume in 1/mm)
SubjectLoader = Callable[[str], "Subject"]


class ModelBuilder(Protocol):
    """Builds the shape model and atlas from the plugin's default population; returns the model
    file's path. ``settings`` are keyword arguments of :func:`clgs.shape.builder.build_model`."""

    def __call__(self, out_path: str | None = None, force: bool = False, **settings: Any) -> str: ...


class SubjectFromMesh(Protocol):
    """A Subject (with a CT volume) from a surface file, or a tuple whose first item is one. May
    also take ``units=`` ("mm", "cm", "m", "in") and ``space=`` ("RAS" or "LPS")."""

    def __call__(self, path: Any, seed: int = 0, **options: Any) -> Subject | tuple: ...


#: the widest closing radius (voxels) a scene may ask for: wider ones fill a bone's real hollows
MAX_CLOSING = 8


class SceneError(InputError):
    """A scene setting of an anatomy is missing its shape, out of range or unknown."""


class AnatomyError(InputError, TypeError):
    """An :class:`Anatomy` record field of the wrong kind (e.g. a loader that is not callable)."""


def _number(key, value, *, positive=True, integer=False, finite=True):
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not _is_numpy_number(value):
        raise SceneError(f"scene {key!r} must be a number, got {value!r}")
    if (finite or integer) and not math.isfinite(float(value)):
        raise SceneError(f"scene {key!r} must be finite, got {value!r}")
    if integer:
        if float(value) != int(value):
            raise SceneError(f"scene {key!r} must be a whole number, got {value!r}")
        value = int(value)
    else:
        value = float(value)
    if positive and not value > 0:
        raise SceneError(f"scene {key!r} must be positive, got {value!r}")
    return value


def _is_numpy_number(value) -> bool:
    return type(value).__module__ == "numpy" and hasattr(value, "dtype") and getattr(value, "ndim", 1) == 0


def _vector(key, value, n, axes, **kw):
    try:
        items = list(value)
    except TypeError:
        raise SceneError(f"scene {key!r} must be {n} numbers ({axes}), got {value!r}") from None
    if len(items) != n:
        raise SceneError(f"scene {key!r} must be {n} numbers ({axes}), got {len(items)}: {value!r}")
    return tuple(_number(key, v, **kw) for v in items)


@dataclass(frozen=True)
class Scene:
    """An anatomy's default scan and reconstruction settings, checked when made.

    TIGRE's names: ``mode`` ("cone" or "parallel"), ``DSO``/``DSD`` (mm, source to origin and to
    detector; cone beam needs DSD > DSO), ``nDetector``/``dDetector``/``offDetector`` (V, U: pixels,
    mm per pixel, mm), ``nVoxel``/``dVoxel``/``offOrigin`` (Z, Y, X: the grid the detector was sized
    for). Then ``n_views`` and ``arc_deg`` (the default views over an arc in (0, 360] degrees),
    ``surface_level`` (bone iso-level, 1/mm), ``surface_closing`` (the widest radius, voxels, of the
    closing that seals gaps in a bone's wall before its cavities are filled: for one bone with a
    marrow cavity, the femur's 3; unset or 0 for anatomies of several bones, which a closing
    could join; :func:`clgs.anatomy.evaluation.bone_mask`), ``density`` (uniform attenuation, 1/mm,
    of a surface without a CT model) and ``n_detector`` (pixels across when clgs sizes the detector
    itself).

    Every field may be left unset (None): clgs's own default applies. A Scene also reads like the
    dict plugins used to give (``scene.get("n_views", 50)``, ``"nVoxel" in scene``, ``dict(scene)``:
    the set fields only); :meth:`from_dict` makes one from such a dict."""

    mode: str | None = None
    DSO: float | None = None
    DSD: float | None = None
    nDetector: tuple | None = None
    dDetector: tuple | None = None
    offDetector: tuple | None = None
    nVoxel: tuple | None = None
    dVoxel: tuple | None = None
    offOrigin: tuple | None = None
    n_views: int | None = None
    arc_deg: float | None = None
    surface_level: float | None = None
    surface_closing: int | None = None
    density: float | None = None
    n_detector: int | None = None

    def __post_init__(self):
        checks = {
            "DSO": _number, "DSD": _number,
            "nDetector": lambda k, v: _vector(k, v, 2, "V, U pixels", integer=True),
            "dDetector": lambda k, v: _vector(k, v, 2, "V, U mm"),
            "offDetector": lambda k, v: _vector(k, v, 2, "V, U mm", positive=False),
            "nVoxel": lambda k, v: _vector(k, v, 3, "Z, Y, X voxels", integer=True),
            "dVoxel": lambda k, v: _vector(k, v, 3, "Z, Y, X mm"),
            "offOrigin": lambda k, v: _vector(k, v, 3, "Z, Y, X mm", positive=False),
            "n_views": lambda k, v: _number(k, v, integer=True),
            "arc_deg": _number, "surface_level": _number,
            "surface_closing": lambda k, v: _number(k, v, positive=False, integer=True),
            "density": _number, "n_detector": lambda k, v: _number(k, v, integer=True),
        }
        if self.mode is not None and self.mode not in ("cone", "parallel"):
            raise SceneError(f"scene 'mode' must be 'cone' or 'parallel', got {self.mode!r}")
        for key, check in checks.items():
            value = getattr(self, key)
            if value is not None:
                object.__setattr__(self, key, check(key, value))
        if self.surface_closing is not None and not 0 <= self.surface_closing <= MAX_CLOSING:
            raise SceneError(f"scene 'surface_closing' must be 0 to {MAX_CLOSING} voxels, got {self.surface_closing!r}")
        if self.arc_deg is not None and self.arc_deg > 360:
            raise SceneError(f"scene 'arc_deg' must be in (0, 360] degrees, got {self.arc_deg!r}")
        if (self.mode or "cone") == "cone" and self.DSO is not None and self.DSD is not None and self.DSD <= self.DSO:
            raise SceneError(f"scene: a cone-beam detector lies beyond the rotation axis: DSD ({self.DSD:g} mm) "
                             f"must be larger than DSO ({self.DSO:g} mm)")

    @classmethod
    def names(cls) -> tuple:
        """The valid setting names, in order."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def from_dict(cls, settings: Mapping | None) -> Scene:
        """A Scene from a dict of settings (how plugins gave it before); an unknown key is a
        :class:`SceneError` naming the valid ones."""
        if settings is None:
            return cls()
        if isinstance(settings, Scene):
            return settings
        if not isinstance(settings, Mapping):
            raise SceneError(f"scene must be a clgs.anatomy.Scene or a dict of its settings, got "
                             f"{type(settings).__name__}")
        unknown = sorted(str(k) for k in settings if k not in cls.names())
        if unknown:
            raise SceneError(f"unknown scene setting(s) {', '.join(map(repr, unknown))}; valid: "
                             f"{', '.join(cls.names())}")
        return cls(**dict(settings))

    def to_dict(self) -> dict:
        """The set fields (lists for the vectors), e.g. for JSON."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.items()}

    def geometry_settings(self) -> dict:
        """The set TIGRE geometry names only (for :class:`clgs.geometry.Geometry`)."""
        keep = ("mode", "DSO", "DSD", "nDetector", "dDetector", "offDetector", "nVoxel", "dVoxel", "offOrigin")
        return {k: v for k, v in self.items() if k in keep}

    # ---- the dict-like reading of old plugins and old callers
    def __getitem__(self, key):
        if key not in self.names() or getattr(self, key) is None:
            raise KeyError(key)
        return getattr(self, key)

    def get(self, key, default=None):
        value = getattr(self, key, None) if key in self.names() else None
        return default if value is None else value

    def keys(self):
        return [k for k in self.names() if getattr(self, k) is not None]

    def items(self):
        return [(k, getattr(self, k)) for k in self.keys()]

    def __contains__(self, key) -> bool:
        return key in self.keys()

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __len__(self) -> int:
        return len(self.keys())

    def __bool__(self) -> bool:
        return True


_LOADER_FIELDS = {
    "load_template": "() -> Template", "load_shape_model": "() -> ShapeModel or None",
    "load_atlas": "() -> DensityAtlas or None", "population": "() -> list of subject ids",
    "test_subjects": "() -> list of held-out subject ids", "load_subject": "(subject_id) -> Subject",
    "build_model": "(out_path=None, force=False, **settings) -> model path",
    "subject_from_mesh": "(path, seed=0) -> Subject",
}


@dataclass
class Anatomy:
    """One anatomy (a bone) supplied by a plugin; checked when made (:class:`AnatomyError`,
    :class:`SceneError`).

    name: the CLI group name (``clgs <name> ...``), lower-case, unique across plugins.
    summary: one line for ``clgs anatomies`` and the group's help.
    version: the plugin's version (shown by ``clgs anatomies``).
    load_template, load_shape_model, load_atlas, population, test_subjects, load_subject,
    build_model, subject_from_mesh: lazy loaders, typed above (:data:`TemplateLoader`, ...,
    :class:`ModelBuilder`, :class:`SubjectFromMesh`). Without ``subject_from_mesh``, ``clgs <name>
    simulate --mesh`` fills the surface with a uniform attenuation ``scene.density``.
    scene: a :class:`Scene` (a dict of its settings is turned into one).
    commands: deprecated; extra click commands for the anatomy's group. Use the hook
        ``register_anatomy_commands`` (:mod:`clgs.anatomy.hookspecs`) instead.
    package: distribution that provided it (filled in by the plugin manager).
    model_path: where the built model lives or will live (shown by ``clgs anatomies``).
    population_model: the object behind the loaders, when there is one
        (:class:`clgs.anatomy.population.SurfacePopulation`).
    """

    name: str
    summary: str
    version: str = "0"
    load_template: TemplateLoader | None = None
    load_shape_model: ShapeModelLoader | None = None
    load_atlas: AtlasLoader | None = None
    population: SubjectIds | None = None
    test_subjects: SubjectIds | None = None
    load_subject: SubjectLoader | None = None
    build_model: ModelBuilder | None = None
    scene: Scene = field(default_factory=Scene)
    commands: list = field(default_factory=list)
    package: str = ""
    model_path: str | None = None
    subject_from_mesh: SubjectFromMesh | None = None
    population_model: Any = None

    def __post_init__(self):
        for key in ("name", "summary", "version", "package"):
            if not isinstance(getattr(self, key), str):
                raise AnatomyError(f"Anatomy {key} must be a string, got {type(getattr(self, key)).__name__}")
        for key, signature in _LOADER_FIELDS.items():
            value = getattr(self, key)
            if value is not None and not callable(value):
                raise AnatomyError(f"anatomy {self.name!r}: {key} must be a callable {signature} or None, got "
                                   f"{type(value).__name__}")
        if self.model_path is not None:
            import os

            self.model_path = os.fspath(self.model_path)
        self.scene = Scene.from_dict(self.scene)
        self.commands = list(self.commands or [])
        if self.commands:
            warnings.warn(f"anatomy {self.name!r}: Anatomy(commands=...) is deprecated; add commands with the hook "
                          "register_anatomy_commands(anatomy, group) (docs/plugins.md)", DeprecationWarning,
                          stacklevel=3)


@dataclass(frozen=True)
class AnatomyParts:
    """What a shape-guided reconstruction uses of an anatomy: the ``template`` (required), its
    ``shape_model`` and density ``atlas`` (each None when absent) and the anatomy they came from,
    if any (its scene gives the bone level). :meth:`load` reads them from an :class:`Anatomy`;
    :meth:`of` takes either."""

    template: Template
    shape_model: ShapeModel | None = None
    atlas: DensityAtlas | None = None
    anatomy: Anatomy | None = None

    def __post_init__(self):
        if self.template is None:
            raise InputError("AnatomyParts needs a template; the shape-guided method starts from it")

    def __iter__(self):
        """(template, shape_model, atlas), so ``template, model, atlas = parts`` reads them."""
        return iter((self.template, self.shape_model, self.atlas))

    @classmethod
    def load(cls, anatomy: Anatomy) -> AnatomyParts:
        """The parts from an Anatomy's lazy loaders (a progress phase each); any object with the
        record's ``name`` and loaders will do."""
        from clgs.progress import phase

        if not all(hasattr(anatomy, k) for k in ("name", "load_template", "load_shape_model", "load_atlas")):
            raise TypeError(f"expected a clgs.anatomy.Anatomy, got {type(anatomy).__name__}")
        if anatomy.load_template is None:
            raise InputError(f"anatomy {anatomy.name!r} provides no template; the shape-guided method needs one")
        with phase(f"loading the {anatomy.name} template"):
            template = anatomy.load_template()
        model = atlas = None
        if anatomy.load_shape_model is not None:
            with phase(f"loading the {anatomy.name} shape model"):
                model = anatomy.load_shape_model()
        if anatomy.load_atlas is not None:
            with phase(f"loading the {anatomy.name} density atlas"):
                atlas = anatomy.load_atlas()
        return cls(template, model, atlas, anatomy)

    @classmethod
    def of(cls, value) -> AnatomyParts:
        """``value`` as AnatomyParts: kept when it is one, loaded when it is an Anatomy; anything
        else (a tuple included) is a TypeError saying what to give."""
        if isinstance(value, cls):
            return value
        if isinstance(value, Anatomy):
            return cls.load(value)
        raise TypeError(f"expected a clgs.anatomy.Anatomy or clgs.anatomy.AnatomyParts, got {type(value).__name__}; "
                        "wrap a (template, shape_model, atlas) tuple as AnatomyParts(template, shape_model, atlas)")
