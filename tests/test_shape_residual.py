"""The residual deformation beyond a shape model's span (clgs.shape.residual): the B-spline's
values and derivatives, its gradients against finite differences, the shape set's centres, inverse
map and checkpoints with it, and fits on the ellipsoid of test_shape_guided: a subject in the
model's span (the residual stays near zero) and one with a bump the model cannot make (the residual
moves the surface onto it)."""
import json

import numpy as np
import pytest
import torch

import test_shape_guided as ellipsoid
from test_shape_guided import _scan, _small, geometry

template, shape_model, tissue_atlas = ellipsoid.template, ellipsoid.shape_model, ellipsoid.tissue_atlas

BUMP_CENTRE = np.array([14.0, 0.0, 4.0])  # on the ellipsoid's surface (semi-axes 14, 10, 22 mm)


def _bump_sdf(template, pts, height=3.0, width=5.0):
    """The ellipsoid with a smooth bump ``height`` mm high on its +x side."""
    d2 = ((np.asarray(pts) - BUMP_CENTRE) ** 2).sum(-1)
    return template.sdf_at(pts) - height * np.exp(-d2 / (2 * width ** 2))


def _bump_scan(template, n_views=8):
    from clgs.io.scan import Scan
    from clgs.ops.ct_projector import CTProjector

    geo = geometry(n_views, 48)
    pts = geo.volume_grid(scene=False).points()
    r = np.linalg.norm(pts[..., :2], axis=-1)
    truth = np.where(_bump_sdf(template, pts) < 0, 0.05, np.where(r < 28.0, 0.01, 0.0)).astype(np.float32)
    return Scan(geo, np.asarray(CTProjector(geo).forward(truth), np.float32), truth=truth)


def _cfg(**kw):
    from clgs.methods.shape_guided import ShapeGuidedConfig

    base = {k: v for k, v in _small(iterations=1, alpha_init_iterations=40, residual="on",
                                    residual_init_iterations=80).items() if k != "progress"}
    base.update(kw)
    return ShapeGuidedConfig(**base)


def test_probe(template, shape_model, tissue_atlas):
    import trimesh
    from clgs.methods.shape_guided import build_trainer, surface_displacement_parts
    parts = (template, shape_model, tissue_atlas)
    with torch.no_grad():
        u = shape_model.displacement(torch.tensor([1.0, -0.8]))
        tv = template.vertices + shape_model.sample(u, torch.as_tensor(template.vertices, dtype=torch.float32)).numpy()
    truth_mesh = trimesh.Trimesh(tv, template.faces)
    scan = _scan(template, alpha=(1.0, -0.8), shape_model=shape_model)
    for ai in (40, 150):
        for lam, lr, b in ((1e-4, 0.2, 1.0), (1e-4, 0.2, 0.1), (1e-3, 0.2, 0.1)):
            s = build_trainer(scan, parts, _cfg(lambda_residual=lam, lr_residual=lr, residual_bending=b, alpha_init_iterations=ai)).sets[0]
            p = surface_displacement_parts(template, s)
            r = np.linalg.norm(p["residual_mm"], axis=1)
            dm = np.abs(trimesh.proximity.signed_distance(truth_mesh, template.vertices + p["model_mm"])).mean()
            dr = np.abs(trimesh.proximity.signed_distance(truth_mesh, p["vertices"])).mean()
            print(ai, lam, lr, b, "res mean/max", r.mean(), r.max(), "surface model", dm, "with res", dr, s.alpha.detach().numpy())
