"""Anatomy plugins and what they build on: the hooks (:mod:`.hookspecs`), the plugin manager
(:mod:`.plugins`), the typed records :class:`Anatomy`, :class:`Scene` and :class:`AnatomyParts`
(:mod:`.record`), the tissue model of a bone's CT (:mod:`.phantom`), rigid alignment of surfaces
(:mod:`.alignment`), a population of real surfaces as an anatomy (:mod:`.population`, declared in
one call with :func:`population_anatomy`), simulated scans of a subject (:mod:`.simulation`) and
the evaluation of a reconstruction against its truth (:mod:`.evaluation`).

A plugin needs only ``from clgs.anatomy import Anatomy, Scene, hookimpl`` (docs/plugins.md).

May import: :mod:`clgs.shape`, :mod:`clgs.ct`, :mod:`clgs.ops`, :mod:`clgs.metrics`,
:mod:`clgs.mesh`, :mod:`clgs.io`, :mod:`clgs.geometry`. Not fit, methods or the CLI. This
package's own import stays light (no torch, no pyopencl): it is read to list plugins.
"""
from clgs.anatomy.hookspecs import hookimpl
from clgs.anatomy.population_plugin import PopulationAnatomy, population_anatomy
from clgs.anatomy.record import Anatomy, AnatomyError, AnatomyParts, Scene, SceneError

__all__ = ["Anatomy", "AnatomyError", "AnatomyParts", "Scene", "SceneError", "hookimpl", "population_anatomy",
           "PopulationAnatomy"]
