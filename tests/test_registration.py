"""Templates (mesh -> label / signed distance) and the diffeomorphic SVF registration."""
import numpy as np
import pytest
import torch

from clgs.shape.model import exp_velocity, sample_field
from clgs.shape.registration import RegistrationSettings, register
from clgs.shape.template import (
    Subject,
    Template,
    box_grid,
    grid_points,
    mesh_from_sdf,
    mesh_to_label,
    mesh_to_sdf,
    vertex_normals,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _sphere_mesh(radius=10.0, centre=(1.0, -2.0, 3.0)):
    shape, sp, org = box_grid(np.array(centre) - radius - 4, np.array(centre) + radius + 4, spacing=0.7)
    p = grid_points(shape, sp, org)
    return mesh_from_sdf(np.linalg.norm(p - centre, axis=-1) - radius, sp, org)


def test_mesh_to_label_and_sdf_of_a_sphere():
    centre, r = np.array([1.0, -2.0, 3.0]), 10.0
    v, f = _sphere_mesh(r, centre)
    shape, sp, org = box_grid(centre - 16, centre + 16, spacing=2.0)
    p = grid_points(shape, sp, org)
    exact = np.linalg.norm(p - centre, axis=-1) - r
    label = mesh_to_label(v, f, shape, sp, org)
    clear = np.abs(exact) > 0.3  # the faceted mesh lies within ~0.1 mm of the sphere
    np.testing.assert_array_equal(label[clear], exact[clear] < 0)
    sdf = mesh_to_sdf(v, f, shape, sp, org)
    near = np.abs(exact) < 2 * sp[0]  # exact point-triangle distances within 3 cells of the surface
    assert np.abs(sdf - exact)[near].max() < 0.1
    assert np.abs(sdf - exact).max() < 1.5  # distance transform far away: about a voxel
    n = vertex_normals(v, f)
    radial = (v - centre) / np.linalg.norm(v - centre, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", n, radial).min() > 0.95  # outward


def test_mesh_to_label_handles_vertices_on_grid_lines():
    """Marching-cubes meshes on the same grid put vertices exactly on voxel columns."""
    shape, sp, org = (14, 15, 16), (2.0, 2.0, 2.0), (-13.0, -14.0, -15.0)
    p = grid_points(shape, sp, org)
    sdf = np.maximum(np.abs(p).max(-1) - 8.0, -(np.linalg.norm(p[..., :2], axis=-1) - 3.0))  # box with a tunnel
    v, f = mesh_from_sdf(sdf, sp, org)
    label = mesh_to_label(v, f, shape, sp, org)
    off = np.abs(sdf) > 1e-9  # nodes exactly on the surface may go either way
    assert off.sum() > 0.9 * sdf.size
    np.testing.assert_array_equal(label[off], sdf[off] < 0)


def test_template_roundtrip_and_queries(tmp_path):
    v, f = _sphere_mesh(8.0, (0.0, 0.0, 0.0))
    t = Template.from_mesh(v, f, spacing=1.5, margin=6.0, name="ball")
    assert t.shape == t.label.shape == t.sdf.shape
    assert t.sdf_at(np.array([[0.0, 5.0, 0.0]]))[0] == pytest.approx(-3.0, abs=0.15)
    assert t.sdf_at(np.array([[100.0, 0, 0]]))[0] > 80  # outside the grid: grows with distance
    np.testing.assert_allclose(t.normal_at(np.array([[8.0, 0, 0]])), [[1, 0, 0]], atol=0.05)
    g = t.grid()
    assert g.shape == t.shape and g.origin == t.origin[::-1]
    t.save(tmp_path / "t.npz")
    t2 = Template.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(t2.sdf, t.sdf)
    assert t2.spacing == t.spacing and t2.origin == t.origin and t2.name == "ball"
    assert t2.content_hash() == t.content_hash()
    with pytest.raises(ValueError, match="same"):
        Template(t.label[:-1], t.sdf, v, f, t.spacing, t.origin)
    with pytest.raises(ValueError, match="faces index"):
        Subject("x", v, f + len(v))


# ---------------------------------------------------------------------------------- registration
def _toy_template():
    shape, sp, org = box_grid([-40, -30, -30], [40, 30, 30], spacing=2.5)
    p = grid_points(shape, sp, org)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    body = (np.sqrt((x / 30) ** 2 + (y / 18) ** 2 + (z / 14) ** 2) - 1) * 14
    hole = 5 - np.sqrt((x - 12) ** 2 + y ** 2)
    v, f = mesh_from_sdf(np.maximum(body, hole), sp, org)
    return Template.from_mesh(v, f, spacing=sp, shape=shape, origin=org)


def _register(template, vertices, max_cells=28, settings=None):
    mshape, msp, morg = template.model_grid(max_cells)
    fixed = mesh_to_sdf(template.vertices, template.faces, mshape, msp, morg)
    lo = np.minimum(vertices.min(0), template.bounds()[0]) - 8
    hi = np.maximum(vertices.max(0), template.bounds()[1]) + 8
    g = box_grid(lo, hi, spacing=msp[0])
    moving = mesh_to_sdf(vertices, template.faces, *g)
    r = register(fixed, msp, morg, moving, g[1], g[2], settings=settings, surface_points=template.vertices)
    return r, (mshape, msp, morg), fixed


def test_registration_recovers_a_known_deformation():
    t = _toy_template()
    mshape, msp, morg = t.model_grid(24)
    P = torch.as_tensor(grid_points(mshape, msp, morg), dtype=torch.float32)
    v_true = 1.5 * torch.stack([4 * torch.sin(P[..., 1] / 25 + 0.3) * torch.cos(P[..., 2] / 30),
                                3 * torch.cos(P[..., 0] / 30), 3 * torch.sin(P[..., 0] / 35 + P[..., 1] / 40)], 0)
    u_true = exp_velocity(v_true, msp)
    verts = torch.as_tensor(t.vertices, dtype=torch.float32)
    subject = (verts + sample_field(u_true, verts, msp, morg)).numpy().astype(np.float64)
    r, (shape, sp, org), fixed = _register(t, subject, max_cells=24,
                                           settings=RegistrationSettings(levels=(12, 0), iterations=(60, 40)))
    assert r.velocity.shape == (3,) + tuple(shape) and sp == msp
    u = exp_velocity(torch.as_tensor(r.velocity), sp)
    err = (u - u_true).norm(dim=0).numpy()
    bone = fixed < 3.0  # the bone and a thin band around it, where the images say something
    cell = sp[0]
    assert float(u_true.norm(dim=0).numpy()[bone].mean()) > 1.3 * cell  # the truth moves over a cell
    assert err[bone].mean() < 0.7 * cell  # (sliding along the surface is not seen by any shape loss)
    assert r.residuals["surface_mean_mm"] < 0.1 * cell
    assert r.residuals["dice"] > 0.98
    assert r.residuals["min_jacobian"] > 0


def test_registration_of_the_template_to_itself_is_identity():
    t = _toy_template()
    r, (shape, sp, org), _ = _register(t, t.vertices, max_cells=20,
                                       settings=RegistrationSettings(levels=(10, 0), iterations=(20, 20)))
    assert np.abs(r.velocity).max() < 0.2 * sp[0]
    assert r.residuals["surface_mean_mm"] < 0.1 * sp[0]


def test_registration_rejects_bad_input():
    sdf = np.zeros((5, 6, 7), np.float32)
    bad = sdf.copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        register(sdf, (1, 1, 1), (0, 0, 0), bad, (1, 1, 1), (0, 0, 0))
    with pytest.raises(ValueError):
        RegistrationSettings(levels=(8, 0), iterations=(10,))
