"""View sets: which angles a simulated scan takes. A count spread over an arc (the papers' 5 and
10 views over 180 degrees), an explicit list of degrees, or a named clinical set (the AP and
lateral radiographs of orthopaedics, an oblique added, a C-arm sweep over a limited arc).

Angles follow :mod:`clgs.geometry`: at 0 degrees the source lies on +x (a lateral view of a bone
along z, x across it), at 90 degrees on +y (an antero-posterior view)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from clgs.errors import InputError

#: named clinical view sets (degrees); limited arcs include both ends, as a C-arm sweeps them
CLINICAL_SETS = {
    "ap-lat": (0.0, 90.0),  # lateral + antero-posterior: the two radiographs of orthopaedics
    "ap-oblique-lat": (0.0, 45.0, 90.0),  # with an oblique between them
    "carm5": (0.0, 22.5, 45.0, 67.5, 90.0),  # a C-arm sweep of 5 views over 90 degrees
}


@dataclass(frozen=True)
class ViewSet:
    """A set of view angles with a short key for file names and tables."""

    key: str
    degrees: tuple

    @property
    def radians(self) -> list:
        return [math.radians(d) for d in self.degrees]

    @property
    def n_views(self) -> int:
        return len(self.degrees)

    def describe(self) -> str:
        return f"{self.n_views} views at " + ", ".join(f"{d:g}" for d in self.degrees) + " deg"


def parse_degrees(text: str) -> tuple:
    """'0,90' -> (0.0, 90.0): explicit view angles in degrees, each finite, no repeats."""
    try:
        vals = tuple(float(x) for x in str(text).replace(" ", "").split(",") if x != "")
    except ValueError:
        raise InputError(f"angles {text!r}: give degrees separated by commas, e.g. 0,90 (AP + lateral)") from None
    if not vals or not all(math.isfinite(v) for v in vals):
        raise InputError(f"angles {text!r}: give one or more finite degrees separated by commas, e.g. 0,90")
    wrapped = [round(v % 360.0, 9) for v in vals]
    if len(set(wrapped)) != len(wrapped):
        raise InputError(f"angles {text!r}: a view is repeated (angles are taken modulo 360)")
    return vals


def arc_degrees(n_views: int, arc_deg: float) -> tuple:
    """``n_views`` spread over ``arc_deg`` with the end excluded (the papers' convention: 5 views
    over 180 degrees are 0, 36, ..., 144)."""
    n = int(n_views)
    if n < 1:
        raise InputError(f"views must be at least 1, got {n_views}")
    return tuple(arc_deg * i / n for i in range(n))


def view_set(spec) -> ViewSet:
    """A view set from a spec: a count (over 180 degrees, the papers' sets; key = the count), a
    name of :data:`CLINICAL_SETS`, or an explicit list of degrees ('0,90'; key 'deg0-90')."""
    if isinstance(spec, ViewSet):
        return spec
    if isinstance(spec, int) or (isinstance(spec, str) and spec.strip().isdigit()):
        n = int(spec)
        return ViewSet(str(n), arc_degrees(n, 180.0))
    text = str(spec).strip()
    if text in CLINICAL_SETS:
        return ViewSet(text, CLINICAL_SETS[text])
    if "," in text:
        deg = parse_degrees(text)
        return ViewSet("deg" + "-".join(f"{d:g}" for d in deg), deg)
    raise InputError(f"view set {spec!r}: give a count (over 180 degrees), degrees such as 0,90, or one of "
                     f"{', '.join(CLINICAL_SETS)}")
