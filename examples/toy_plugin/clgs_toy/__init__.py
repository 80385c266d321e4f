"""clgs-toy: a minimal, complete anatomy plugin for clgs.

The "toy bone" is an ellipsoid (about 64 x 30 x 24 mm) with a cylindrical hole through it and a
slight bend, with a cortical shell, cancellous interior and a cylinder of soft tissue around it.
Its population is procedural: subject ``NN`` draws its shape and densities from a generator
seeded with ``1000 + NN``, so the plugin ships no data and ``clgs toy build-model`` takes seconds.
Subjects 00-07 build the model; 08 and 09 are held out.

Everything a plugin gives clgs is one :class:`clgs.anatomy.Anatomy` returned by the hook
``clgs_anatomies`` (its loaders are plain functions, called only when a command needs them), and
its own command ``clgs toy params`` through the hook ``register_anatomy_commands``. This
module imports nothing heavy at import time (``clgs --help`` imports it to list the anatomy).
"""
from __future__ import annotations

import os
import sys

from clgs.anatomy import Anatomy, Scene, hookimpl

__version__ = "0.1.0"

NAME = "toy"
SUBJECTS = [f"{i:02d}" for i in range(10)]
TEST_SUBJECTS = ["08", "09"]
GENERATOR_VERSION = 1  # bump when the shapes or densities change (old models are then rebuilt)

# the CT grid (also the template grid): (Z, Y, X) voxels of 2 mm centred on the rotation axis
SHAPE = (40, 40, 56)
SPACING = (2.0, 2.0, 2.0)
ORIGIN = tuple(-0.5 * (n - 1) * s for n, s in zip(SHAPE, SPACING))

# registration and PCA settings for this small anatomy (keyword arguments of build_model)
BUILD_SETTINGS = {"max_cells": 24, "variance": 0.95,
                  "registration": {"levels": [12, 0], "iterations": [40, 30]}}

SCENE = Scene(mode="cone", DSO=1000.0, DSD=1500.0, nDetector=(96, 128), dDetector=(2.0, 2.0), n_views=50,
              arc_deg=180.0, surface_level=0.03)


def model_dir() -> str:
    """Where the built model lives: $CLGS_TOY_HOME or ~/.cache/clgs/toy."""
    return os.environ.get("CLGS_TOY_HOME") or os.path.join(os.path.expanduser("~"), ".cache", "clgs", "toy")


def model_path() -> str:
    return os.path.join(model_dir(), f"toy-model-g{GENERATOR_VERSION}.npz")


# --------------------------------------------------------------------------------------- shapes
def parameters(sid) -> dict:
    """The generating parameters of subject ``sid`` (mean shape for sid=None)."""
    import numpy as np

    z = np.zeros(10) if sid is None else np.random.default_rng(1000 + int(sid)).standard_normal(10)
    z = np.clip(z, -2.5, 2.5)
    return {
        "semi_axes_mm": [32.0 + 3.0 * z[0], 15.0 + 1.5 * z[1], 12.0 + 1.2 * z[2]],
        "hole_radius_mm": 4.0 + 0.5 * z[3],
        "hole_x_mm": 12.0 + 2.0 * z[4],
        "bend_mm": 3.0 * z[5],
        "cortex_mm": 2.5 + 0.4 * z[6],
        "cortical": 0.045 + 0.004 * z[7],  # attenuation, 1/mm
        "cancellous": 0.020 + 0.003 * z[8],
        "soft_tissue": 0.019 + 0.001 * z[9],
    }


def _implicit(points, p):
    """A smooth implicit function of the shape (negative inside, about mm near the surface)."""
    import numpy as np

    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    a, b, c = p["semi_axes_mm"]
    zb = z - p["bend_mm"] * (x / a) ** 2
    body = (np.sqrt((x / a) ** 2 + (y / b) ** 2 + (zb / c) ** 2) - 1.0) * min(a, b, c)
    hole = p["hole_radius_mm"] - np.sqrt((x - p["hole_x_mm"]) ** 2 + zb ** 2)
    return np.maximum(body, hole)


def surface(sid):
    """(vertices (x, y, z) mm, faces) of subject ``sid`` (the mean shape for None)."""
    from clgs.shape.template import box_grid, grid_points, mesh_from_sdf

    p = parameters(sid)
    a = max(p["semi_axes_mm"]) + 6.0
    shape, sp, org = box_grid((-a, -a, -a), (a, a, a), spacing=1.0)
    return mesh_from_sdf(_implicit(grid_points(shape, sp, org), p), sp, org)


def load_subject(sid):
    """A :class:`clgs.shape.template.Subject`: surface plus CT (cortex, cancellous bone, soft tissue)."""
    import numpy as np

    from clgs.shape.template import Subject, grid_points, mesh_to_sdf

    sid = str(sid)
    if sid not in SUBJECTS:
        raise KeyError(f"toy: unknown subject {sid!r}; subjects are {', '.join(SUBJECTS)}")
    p = parameters(sid)
    v, f = surface(sid)
    d = mesh_to_sdf(v, f, SHAPE, SPACING, ORIGIN)
    pts = grid_points(SHAPE, SPACING, ORIGIN)
    limb = np.sqrt((pts[..., 1] / 34.0) ** 2 + (pts[..., 2] / 30.0) ** 2) < 1.0
    ct = np.where(limb, p["soft_tissue"], 0.0)
    ct = np.where(d < 0, p["cancellous"], ct)
    ct = np.where((d < 0) & (d > -p["cortex_mm"]), p["cortical"], ct)
    return Subject(sid, v, f, volume=ct.astype(np.float32), spacing=SPACING, origin=ORIGIN,
                   meta={"anatomy": NAME, "held_out": sid in TEST_SUBJECTS, "parameters": p})


_template = None


def load_template():
    """The mean shape on the CT grid."""
    global _template  # noqa: PLW0603 - loaded once per process
    if _template is None:
        from clgs.shape.template import Template

        v, f = surface(None)
        _template = Template.from_mesh(v, f, spacing=SPACING, shape=SHAPE, origin=ORIGIN, name=NAME,
                                       meta={"source": "toy mean parameters"})
    return _template


def population():
    return [s for s in SUBJECTS if s not in TEST_SUBJECTS]


def test_subjects():
    return list(TEST_SUBJECTS)


# --------------------------------------------------------------------------------------- model
def build_model(out_path=None, force: bool = False, **settings) -> str:
    """Register the 8 model subjects to the template, PCA, density atlas (a few seconds)."""
    from functools import partial

    from clgs.shape.builder import build_model as build

    kwargs = dict(BUILD_SETTINGS)
    kwargs.update(settings)
    subjects = {sid: partial(load_subject, sid) for sid in population()}
    return build(load_template(), subjects, out_path or model_path(), force=force,
                 extra_meta={"anatomy": NAME, "generator_version": GENERATOR_VERSION}, **kwargs)


def _ensure_model() -> str:
    path = model_path()
    if not os.path.exists(path):
        print(f"toy: building the model at {path} (first use, a few seconds)", file=sys.stderr)
        build_model(progress=False)
    return path


def load_shape_model():
    from clgs.shape.model import load_model

    return load_model(_ensure_model())[0]


def load_atlas():
    from clgs.shape.model import load_model

    return load_model(_ensure_model(), need_shape_model=False)[1]


# --------------------------------------------------------------------------------------- plugin
def _params_command():
    import click

    @click.command("params")
    @click.argument("subject", required=False)
    def params(subject):
        """Print the generating parameters of SUBJECT (the mean shape when omitted)."""
        import json

        click.echo(json.dumps(parameters(subject), indent=1))

    return params


@hookimpl
def clgs_anatomies():
    return [Anatomy(
        name=NAME, summary="toy bone: a procedural ellipsoid with a hole (8 model subjects, 2 held out)",
        version=__version__, load_template=load_template, load_shape_model=load_shape_model,
        load_atlas=load_atlas, population=population, test_subjects=test_subjects, load_subject=load_subject,
        build_model=build_model, scene=SCENE, model_path=model_path())]


@hookimpl
def register_anatomy_commands(anatomy, group):
    """``clgs toy params``: this plugin's own command, added to its anatomy's group only."""
    if anatomy.name == NAME:
        group.add_command(_params_command())
