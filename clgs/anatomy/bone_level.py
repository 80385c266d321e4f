"""The bone iso-level (1/mm) at which a reconstruction's bone surface is taken, and where it came
from. One rule for every place that writes or measures a bone surface, so the file written and the
figure reported are always the same surface.

The level is chosen, first found first (:func:`choose_level`):

``user``    given by the user (``--surface-level``, ``surface_level=``);
``scan``    the level a scan's true surface was made at (``meta['truth_surface_level']``, written by
            ``clgs simulate --surface-level``);
``scene``   the anatomy plugin's ``scene.surface_level``;
``truth``   a simulated scan's true volume: the upper of its 3-class Otsu thresholds (air, soft
            tissue, bone); for a truth of two values (a surface filled with one density) Otsu's
            threshold; half way to the next density up where the truth has a gap there
            (:func:`truth_level`);
``atlas``   the anatomy's density atlas: half way between its soft tissue just outside the
            template's bone and its bone just inside (:func:`atlas_level`).

Never a percentile of the reconstruction: in a mostly-air volume such a level lies in the soft
tissue and the "bone" surface traces the limb. With none of these there is no bone level, and no
bone surface is written.

The level carries the anatomy's ``scene.surface_closing`` (whatever its source): how wide a gap in
the bone's wall the surface may seal before the cavities are filled
(:func:`clgs.anatomy.evaluation.bone_mask`); 0 without an anatomy or where it names none.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from clgs.anatomy.record import MAX_CLOSING, Scene
from clgs.errors import InputError

__all__ = ["BoneLevel", "SOURCES", "choose_level", "anatomy_closing", "with_closing", "truth_level", "atlas_level"]

#: what each source means, for reports and documentation
SOURCES = {
    "user": "given by the user",
    "scan": "the level the scan's true surface was made at (meta truth_surface_level)",
    "scene": "the anatomy's scene.surface_level",
    "truth": "the upper 3-class Otsu threshold of the scan's true volume",
    "atlas": "half way between the density atlas's soft tissue and bone at the template's surface",
}


@dataclass(frozen=True)
class BoneLevel:
    """A bone iso-level (1/mm), its source (a key of :data:`SOURCES`) and the widest closing
    (voxels) the bone surface at it may use (the anatomy's ``scene.surface_closing``; 0: none)."""

    value: float
    source: str
    closing: int = 0

    def __post_init__(self):
        if self.source not in SOURCES:
            raise ValueError(f"unknown bone-level source {self.source!r}; one of {', '.join(SOURCES)}")
        if not (np.isfinite(self.value) and self.value > 0):
            raise ValueError(f"a bone level must be a positive attenuation (1/mm), got {self.value!r}")
        if isinstance(self.closing, bool) or int(self.closing) != self.closing or self.closing < 0:
            raise ValueError(f"a surface closing is a whole number of voxels >= 0, got {self.closing!r}")
        object.__setattr__(self, "closing", int(self.closing))

    def record(self) -> dict:
        """The fields a report carries: ``surface_level``, ``surface_level_source`` and, where the
        surface may close gaps in the bone's wall, ``surface_closing_max_voxels``."""
        closing = {"surface_closing_max_voxels": self.closing} if self.closing else {}
        return {"surface_level": float(self.value), "surface_level_source": self.source, **closing}

    def describe(self) -> str:
        return f"{self.value:.5g} 1/mm ({self.source}: {SOURCES[self.source]})"


def truth_level(truth) -> float:
    """The upper of the true volume's 3-class Otsu thresholds (Otsu's threshold for a truth of
    two values; a ValueError for a constant one), moved to the middle of the gap above it when the
    truth holds no values there. Otsu's threshold is a histogram bin: on a truth of a few discrete
    densities (soft tissue 0.02, bone 0.05) it is the soft tissue's own value, where a blurred
    reconstruction's tissue lies on both sides; half way to the next density is the edge between
    the two. On a truth of continuous densities (the femur's) the gap is nil and nothing moves."""
    from skimage.filters import threshold_multiotsu, threshold_otsu

    t = np.asarray(truth, np.float32)
    sub = t[:: max(1, t.shape[0] // 64)]
    if float(sub.min()) == float(sub.max()):
        raise ValueError("the true volume is constant: it has no bone level")
    try:
        level = float(threshold_multiotsu(sub, classes=3)[-1])
    except ValueError:  # two values only (a surface filled with one density): bone against air
        level = float(threshold_otsu(sub))
    above = sub[sub > level]
    return 0.5 * (level + float(above.min())) if above.size else level


def atlas_level(atlas, template) -> float:
    """Half way between the atlas's soft tissue and its bone at the template's surface: the median
    of the atlas mean 1 to 3 voxels outside the template's bone (0 for an atlas of the bone alone,
    in air) and the median within 1 voxel inside it. The outer surface of a blurred bone edge lies
    at that half way mark; the femur's atlas gives 0.0269 (soft tissue 0.0202, bone 0.0336)."""
    mean = np.asarray(atlas.mean, np.float32)
    s = float(max(atlas.spacing))
    d = template.sdf_at(atlas.grid().points().reshape(-1, 3)).reshape(mean.shape)
    inside = mean[(d >= -s) & (d < 0)]
    if inside.size == 0:
        raise ValueError("the density atlas holds none of the template's bone: it gives no bone level")
    bone = float(np.median(inside))
    shell = mean[(d > s) & (d <= 3 * s)]
    tissue = shell[shell > 0.25 * bone]  # air around a bone that touches the skin is not tissue
    soft = float(np.median(tissue)) if tissue.size > 0.1 * max(shell.size, 1) else 0.0
    if not bone > soft:
        raise ValueError(f"the density atlas's bone ({bone:.4g} 1/mm) is not denser than the tissue around it "
                         f"({soft:.4g}): it gives no bone level")
    return 0.5 * (soft + bone)


def choose_level(user=None, anatomy=None, truth=None, scan_meta=None, atlas=None, template=None):
    """The bone level (:class:`BoneLevel`) by the module's order, or None when nothing gives one.

    ``anatomy``: an :class:`clgs.anatomy.Anatomy` (its scene, and, when nothing before gives a
    level, its atlas and template, loaded then) or None; ``truth``: a simulated scan's true volume;
    ``scan_meta``: the scan's meta; ``atlas``/``template``: parts already loaded (a shape-guided
    run's). Whatever its source, the level carries the anatomy's ``scene.surface_closing``."""
    found = _level(user, anatomy, truth, scan_meta, atlas, template)
    return None if found is None else replace(found, closing=anatomy_closing(anatomy))


def anatomy_closing(anatomy) -> int:
    """The widest closing (voxels) an anatomy's bone surface may use: its ``scene.surface_closing``,
    0 for None or an anatomy that names none."""
    return Scene.from_dict(getattr(anatomy, "scene", None)).surface_closing or 0


def with_closing(level: BoneLevel | None, closing: int | None) -> BoneLevel | None:
    """``level`` with the widest closing a user gave (``closing``, 0 to ``MAX_CLOSING`` voxels) in
    place of the anatomy's: for a scan that names no anatomy (``clgs reconstruct
    --surface-closing``), or to turn the anatomy's off (0). ``level`` as it is when ``closing`` is
    None."""
    if closing is None:
        return level
    if isinstance(closing, bool) or not isinstance(closing, (int, np.integer)) or not 0 <= closing <= MAX_CLOSING:
        raise InputError(f"surface closing must be a whole number of voxels from 0 to {MAX_CLOSING}, got {closing!r}")
    return None if level is None else replace(level, closing=int(closing))


def _level(user, anatomy, truth, scan_meta, atlas, template):
    if user is not None:
        return BoneLevel(float(user), "user")
    recorded = (scan_meta or {}).get("truth_surface_level")
    if recorded is not None:
        return BoneLevel(float(recorded), "scan")
    level = Scene.from_dict(getattr(anatomy, "scene", None)).surface_level
    if level is not None:
        return BoneLevel(level, "scene")
    if truth is not None:
        try:
            return BoneLevel(truth_level(truth), "truth")
        except ValueError:
            pass
    if atlas is None and anatomy is not None and getattr(anatomy, "load_atlas", None) is not None:
        atlas = anatomy.load_atlas()
    if template is None and atlas is not None and getattr(anatomy, "load_template", None) is not None:
        template = anatomy.load_template()
    if atlas is not None and template is not None:
        try:
            return BoneLevel(atlas_level(atlas, template), "atlas")
        except ValueError:
            return None
    return None
