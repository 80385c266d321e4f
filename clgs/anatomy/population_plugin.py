"""An anatomy plugin from a population of real surfaces in one declarative call.

A plugin whose anatomy is a set of surface files in vertex correspondence (the built-in femur and
patella) gives only its data: files, held-out ids, CT grid, density parameters, frame, scanner.
:func:`population_anatomy` returns a :class:`PopulationAnatomy`, whose ``clgs_anatomies`` is the
plugin's hook implementation::

    PLUGIN = population_anatomy(name="patella", ...)
    population_model = PLUGIN.population_model
    clgs_anatomies = PLUGIN.clgs_anatomies

Light to import: :mod:`clgs.anatomy.population` (numpy, meshes) loads when the hook runs.
"""
from __future__ import annotations

from collections.abc import Callable

from clgs.anatomy.hookspecs import hookimpl
from clgs.anatomy.record import Anatomy, Scene

__all__ = ["PopulationAnatomy", "population_anatomy"]

#: the scene settings that size the detector; any other one given is kept as it is
_SIZING = ("DSO", "DSD", "n_views", "arc_deg", "dDetector")


class PopulationAnatomy:
    """The settings of one population anatomy; its :class:`clgs.anatomy.population.SurfacePopulation`
    is made once, on first use (:meth:`population_model`)."""

    def __init__(self, settings: dict, scene: Scene, params):
        self.settings = settings
        self.scene = scene
        self.params = params
        self._population = None

    @property
    def name(self) -> str:
        return self.settings["name"]

    def population_model(self):
        """The :class:`clgs.anatomy.population.SurfacePopulation` (made on the first call)."""
        if self._population is None:
            from clgs.anatomy.population import SurfacePopulation

            s, scene = dict(self.settings), self.scene
            params = self.params() if callable(self.params) else self.params
            pixel_mm = scene.dDetector[1] if scene.dDetector is not None else float(s["spacing_mm"])
            pop = SurfacePopulation.centred(
                pixel_mm=pixel_mm, n_views=scene.get("n_views", 50), arc_deg=scene.get("arc_deg", 180.0),
                DSO=scene.get("DSO", 1000.0), DSD=scene.get("DSD", 1500.0), params=params, **s)
            given = {k: v for k, v in scene.items() if k not in _SIZING}
            if given:
                pop.scene = Scene.from_dict({**pop.scene.to_dict(), **given})
            self._population = pop
        return self._population

    def anatomy(self) -> Anatomy:
        """The :class:`clgs.anatomy.Anatomy` record (loaders lazy; the model path is computed)."""
        return self.population_model().anatomy()

    @hookimpl
    def clgs_anatomies(self) -> list:
        return [self.anatomy()]


def population_anatomy(*, name: str, summary: str, version: str, data_dir, file_pattern: str, ids, test_ids,
                       shape, spacing_mm: float, params: object | Callable[[], object], frame_offset,
                       scene: Scene | dict | None = None, side_of: Callable | None = None,
                       builder_settings: dict | None = None, notice: str = "") -> PopulationAnatomy:
    """One population anatomy, declared (see the module doc).

    ``data_dir`` / ``file_pattern`` (with ``{id}``) / ``ids`` / ``test_ids``: the subjects' npz files
    (``vertices``, ``faces`` in mm, in vertex correspondence) and the held-out ids (never in the
    model). ``shape`` (Z, Y, X) voxels of ``spacing_mm``: the CT grid, centred on the rotation axis.
    ``params``: :class:`clgs.anatomy.phantom.DensityParams`, or a function returning it (called on
    first use, so the plugin's import stays light). ``frame_offset`` (x, y, z mm): the files' frame
    to the grid centre. ``scene``: a :class:`Scene` (or a dict of its settings): ``DSO``, ``DSD``
    (default 1000, 1500 mm), ``n_views`` (50), ``arc_deg`` (180) and the pixel size ``dDetector``
    (default ``spacing_mm``) size a flat detector that sees the whole grid; any other setting given
    (``surface_level``, ``density``, ...) is kept. ``side_of(vertices) -> (side, mm)``: mirror
    subjects of the other side (:mod:`clgs.anatomy.sides`). ``builder_settings``: keyword arguments
    of :func:`clgs.shape.builder.build_model`. Errors in the settings are raised here, at import."""
    scene = Scene.from_dict(scene)
    if len(tuple(shape)) != 3:
        raise ValueError(f"{name}: shape must be (Z, Y, X) voxels, got {shape!r}")
    unknown = sorted(set(map(str, test_ids)) - set(map(str, ids)))
    if unknown:
        raise ValueError(f"{name}: held-out ids {unknown} are not among the subjects")
    settings = dict(name=name, summary=summary, version=version, data_dir=str(data_dir), file_pattern=file_pattern,
                    ids=list(ids), test_ids=list(test_ids), shape=tuple(shape), spacing_mm=float(spacing_mm),
                    frame_offset=tuple(frame_offset), side_of=side_of, builder_settings=builder_settings,
                    notice=notice)
    return PopulationAnatomy(settings, scene, params)
