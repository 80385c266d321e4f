"""What an anatomy plugin hands to clgs: names, lazy loaders and default scene settings.

Loaders are plain callables so that listing plugins (``clgs --help``, ``clgs anatomies``) never
reads a model from disk. Every file a loader reads is data (npz with ``allow_pickle=False``,
JSON), never code.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional


@dataclass
class Anatomy:
    """One anatomy (a bone) supplied by a plugin.

    name: the CLI group name (``clgs <name> ...``), lower-case, unique across plugins.
    summary: one line for ``clgs anatomies`` and the group's help.
    version: the plugin's version (shown by ``clgs anatomies``).
    load_template: () -> clgs.shape.template.Template (label volume, signed distance, surface mesh, grid in mm).
    load_shape_model: () -> clgs.shape.model.ShapeModel, or None when the plugin has none yet.
    load_atlas: () -> clgs.shape.model.DensityAtlas (mean and variance on the template grid), or None.
    population: () -> list of subject ids usable to build the model (held-out ones excluded).
    test_subjects: () -> list of held-out subject ids (never used to build the model).
    load_subject: (subject_id) -> clgs.shape.template.Subject (surface mesh and CT-like volume).
    build_model: (out_path=None, force=False, **settings) -> path of the built model file (the plugin's
        default population; settings are keyword arguments of clgs.shape.builder.build_model).
    subject_from_mesh: (path, seed=0) -> Subject (with a CT volume) from a surface file, or a tuple
        whose first item is the Subject; when absent ``clgs <name> simulate --mesh`` fills the surface
        with a uniform attenuation ``scene['density']``.
    scene: default scan and reconstruction settings: TIGRE geometry names (mode, DSO, DSD, nDetector,
        dDetector, offDetector), n_views, arc_deg, surface_level (bone iso-level, 1/mm), density.
    commands: extra click commands added to the anatomy's CLI group.
    package: distribution that provided it (filled in by the plugin manager).
    model_path: where the built model lives or will live (shown by ``clgs anatomies``).
    """

    name: str
    summary: str
    version: str = "0"
    load_template: Optional[Callable] = None
    load_shape_model: Optional[Callable] = None
    load_atlas: Optional[Callable] = None
    population: Optional[Callable] = None
    test_subjects: Optional[Callable] = None
    load_subject: Optional[Callable] = None
    build_model: Optional[Callable] = None
    scene: dict = field(default_factory=dict)
    commands: list = field(default_factory=list)
    package: str = ""
    model_path: Optional[str] = None
    subject_from_mesh: Optional[Callable] = None
