"""Left and right: which side each subject of a population is, and mirroring the others into
the template's side, so one shape model holds both.

An anatomy says how to tell the side of one surface (``side_of(vertices) -> (side, measure)``,
e.g. the femur's head offset from its shaft axis, ``clgs_femur.femur_side``); this module decides
the population's side (the side most of the model's subjects are: the template's) and mirrors
every subject of the other side across the sagittal plane through its own centroid (x -> -x, so
it stays where it was on the grid, faces reversed so normals still point out). Subjects whose
side cannot be told are left as they are and say so.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

SIDES = ("left", "right")


def mirror_x(vertices, faces):
    """The surface mirrored across the plane x = its centroid's x: (vertices, faces reversed)."""
    v = np.array(vertices, np.float64, copy=True)
    v[:, 0] = 2.0 * v[:, 0].mean() - v[:, 0]
    return v, np.ascontiguousarray(np.asarray(faces)[:, ::-1])


def decide_sides(meshes: dict, side_of: Callable, model_ids) -> dict:
    """{"template_side", "rule", "subjects": {id: {"side", "measure_mm", "mirrored"}}} for
    ``meshes`` (id -> vertices (V, 3) mm): each subject's side from ``side_of``, the template's side
    the majority of ``model_ids``' decided sides (left on a tie), a subject mirrored when its side
    is decided and not the template's."""
    subjects = {}
    for sid, v in meshes.items():
        side, measure = side_of(np.asarray(v, np.float64))
        subjects[str(sid)] = {"side": side if side in SIDES else "undecided", "measure_mm": round(float(measure), 2)}
    model = [subjects[str(s)]["side"] for s in model_ids if str(s) in subjects]
    counts = {s: model.count(s) for s in SIDES}
    template_side = "right" if counts["right"] > counts["left"] else "left"
    for r in subjects.values():
        r["mirrored"] = r["side"] in SIDES and r["side"] != template_side
    return {"template_side": template_side, "subjects": subjects,
            "rule": getattr(side_of, "rule", "") or "the anatomy's side test; the other side mirrored in x"}
