"""The residual deformation beyond a shape model's span (clgs.shape.residual): the B-spline's
values and derivatives, its gradients against finite differences, the shape set's centres, inverse
map and checkpoints with it, and fits on the ellipsoid of test_shape_guided: a subject in the
model's span (the residual stays near zero) and one with a bump the model cannot make (the residual
moves the surface onto it)."""
import json

import numpy as np
import pytest
import test_shape_guided as ellipsoid
import torch
from test_shape_guided import _scan, _small, geometry

from clgs.anatomy import AnatomyParts

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


def test_the_bspline_reproduces_affine_fields_and_its_bending_is_their_second_derivatives():
    """Coefficients sampled from an affine map give that map on the whole grid (a cubic B-spline
    reproduces linear functions) with zero bending; random coefficients: the analytic second
    derivatives against central differences of the field (a known answer: numpy's)."""
    from clgs.shape.residual import ResidualGrid, control_layout

    shape, spacing = (20, 12, 9), (3.0, 2.0, 2.5)
    g = ResidualGrid(shape, spacing, points=8, dtype=torch.float64)
    counts, h, offsets = control_layout(shape, spacing, 8)
    assert counts == g.n_control and counts[0] == 8 and h == pytest.approx(19 * 3.0 / 5)
    ctrl = [off + h * np.arange(n) for n, off in zip(counts, offsets)]  # control positions (mm) per axis
    cz, cy, cx = np.meshgrid(*ctrl, indexing="ij")
    A = np.array([[0.02, -0.01, 0.03], [0.0, 0.05, -0.02], [0.01, 0.0, -0.04]])
    b = np.array([1.0, -2.0, 0.5])
    theta = torch.as_tensor(np.einsum("ij,jzyx->izyx", A, np.stack([cx, cy, cz])) + b[:, None, None, None])
    pz, py, px = np.meshgrid(*[np.arange(n) * d for n, d in zip(shape, spacing)], indexing="ij")
    want = np.einsum("ij,jzyx->izyx", A, np.stack([px, py, pz])) + b[:, None, None, None]
    np.testing.assert_allclose(g.field(theta).numpy(), want, atol=1e-10)
    assert float(g.bending(theta)) < 1e-20

    fine = ResidualGrid((41, 33, 29), (0.5, 0.6, 0.7), points=6, dtype=torch.float64)
    theta = torch.randn(fine.coefficient_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    r = fine.field(theta).numpy()
    steps = (0.5, 0.6, 0.7)
    for kz, ky, kx in ((2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1)):
        got = fine._apply(theta, kz, ky, kx).numpy()
        want = r
        for axis, k in enumerate((kz, ky, kx)):
            if k == 2:  # the three-point stencil: exact for a cubic within a knot interval
                want = (np.roll(want, -1, axis + 1) - 2 * want + np.roll(want, 1, axis + 1)) / steps[axis] ** 2
            elif k == 1:
                want = np.gradient(want, steps[axis], axis=axis + 1)
        inner = (slice(None), slice(2, -2), slice(2, -2), slice(2, -2))
        err = np.abs(got[inner] - want[inner]).max() / np.abs(want[inner]).max()
        assert err < 0.05, (kz, ky, kx, err)


def test_the_residuals_gradients_match_finite_differences():
    """float64: the field at arbitrary points through the model's sampler, and the prior with its
    bending term, against torch's central differences."""
    from clgs.shape.model import sample_field
    from clgs.shape.residual import ResidualGrid

    g = ResidualGrid((9, 7, 6), (4.0, 4.0, 4.0), points=5, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    theta = torch.randn(g.coefficient_shape, dtype=torch.float64, generator=gen).requires_grad_(True)
    pts = torch.rand(40, 3, dtype=torch.float64, generator=gen) * torch.tensor([20.0, 24.0, 32.0])
    weights = torch.randn(40, 3, dtype=torch.float64, generator=gen)

    def at_points(t):
        return (sample_field(g.field(t), pts, g.spacing, (0.0, 0.0, 0.0)) * weights).sum()

    assert torch.autograd.gradcheck(at_points, (theta,), eps=1e-6, atol=1e-7)
    assert torch.autograd.gradcheck(lambda t: g.prior(t, 2.0), (theta,), eps=1e-6, atol=1e-7)
    assert torch.autograd.gradcheck(g.bending, (theta,), eps=1e-6, atol=1e-9)


def _set(template, shape_model, theta_seed=0, alpha=(0.4, -0.3), size=1.1, points=6):
    from clgs.fit.gaussians import Schedule
    from clgs.shape.gaussian_set import ShapeGuidedSet
    from clgs.shape.initialise import sample_reference_centres
    from clgs.shape.residual import ResidualGrid
    from clgs.shape.size import size_centre

    p = sample_reference_centres(template, 200, seed=0)
    n = len(p)
    grid = ResidualGrid(shape_model.shape, shape_model.spacing, points)
    theta = None
    if theta_seed is not None:
        theta = 1.5 * torch.randn(grid.coefficient_shape, generator=torch.Generator().manual_seed(theta_seed))
    sched = {k: Schedule(0.01) for k in ("alpha", "log_size", "residual", "scales", "quats", "densities")}
    return ShapeGuidedSet(p, np.full((n, 3), 0.02, np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          np.full(n, 0.1, np.float32), shape_model=shape_model, geometry=geometry(),
                          box=(-1.0, 1.0), scale_bounds=(1e-4, 1.0), schedules=sched, alpha=alpha, size=size,
                          size_centre_mm=size_centre(template), residual=grid, residual_theta=theta)


def test_the_sets_centres_add_the_residual_and_the_inverse_map_undoes_it(template, shape_model):
    """centres = c + s (p_ref + u(p_ref) + r(p_ref) - c), checked in float64 from the parts; their
    gradient wrt the coefficients against central differences; the inverse map takes them back."""
    from clgs.shape.model import sample_field

    s = _set(template, shape_model)
    assert s.has_residual
    with torch.no_grad():
        m64 = shape_model.to(torch.float64)
        u = m64.displacement(torch.tensor([0.4, -0.3], dtype=torch.float64), n_squarings=None)
        r = s.residual.to(torch.float64).field(s.params["residual"].double())
        p = s.p_ref.double()
        model_only = p + sample_field(u, p, m64.spacing, m64.origin)
        c, k = s.size_centre.double(), 1.1
        want = c + k * (model_only + sample_field(r, p, m64.spacing, m64.origin) - c)
        got = s.centres_mm().double()
    assert float((want - c - k * (model_only - c)).norm(dim=1).mean()) > 0.5  # the residual moves them
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=0.02)  # the set's squarings: 2, not 4
    g = torch.randn(len(s), 3, generator=torch.Generator().manual_seed(3))
    (s.centres_mm() * g).sum().backward()
    grad = s.params["residual"].grad
    rng = np.random.default_rng(0)
    for idx in [tuple(int(rng.integers(n)) for n in grad.shape) for _ in range(6)]:
        h = 0.05
        with torch.no_grad():
            s.params["residual"][idx] += h
            up = float((s.centres_mm().double() * g).sum())
            s.params["residual"][idx] -= 2 * h
            down = float((s.centres_mm().double() * g).sum())
            s.params["residual"][idx] += h
        assert float(grad[idx]) == pytest.approx((up - down) / (2 * h), rel=2e-3, abs=2e-3)
    with torch.no_grad():
        back = s.to_template(s.centres_mm())
    np.testing.assert_allclose(back.numpy(), s.p_ref.numpy(), atol=0.1)  # two fixed-point steps


def test_a_residual_checkpoint_round_trips_and_another_run_is_refused(template, shape_model):
    a, b = _set(template, shape_model, theta_seed=1), _set(template, shape_model, theta_seed=None)
    b.load_state_dict(a.state_dict())
    with torch.no_grad():
        np.testing.assert_array_equal(a.centres_mm().numpy(), b.centres_mm().numpy())
    assert "residual_mm" in a.to_numpy()
    with pytest.raises(ValueError, match="another residual_points"):
        _set(template, shape_model, theta_seed=None, points=8).load_state_dict(a.state_dict())
    plain = _set(template, shape_model, theta_seed=None)
    del plain.params["residual"]
    with pytest.raises(ValueError, match="with a residual deformation, this run's without"):
        plain.load_state_dict(a.state_dict())


def _residual_after_registration(template, shape_model, tissue_atlas, scan, alpha, monkeypatch):
    """(residual (V, 3) mm at the template's vertices, its signed component along the outward
    normal) that the residual's registration fits to ``scan`` with alpha held at ``alpha`` (the
    alpha registration replaced by that answer)."""
    import trimesh

    import clgs.methods.shape_guided as sg

    monkeypatch.setattr(sg, "fit_initial_alpha", lambda *a, size=None, **k: (np.float32(alpha), size))
    # the test scene is small (2 mm voxels, a 44 mm bone): a finer grid than the femur's 16 points
    # over 477 mm would be, and a prior to match
    cfg = _cfg(fit_size="off", residual_points=12, lambda_residual=1e-3)
    s = sg.build_trainer(scan, AnatomyParts(template, shape_model, tissue_atlas), cfg).sets[0]
    p = sg.surface_displacement_parts(template, s)
    normals = trimesh.Trimesh(p["vertices"] - p["residual_mm"], template.faces, process=False).vertex_normals
    return p["residual_mm"], (p["residual_mm"] * normals).sum(1)


def test_the_residual_stays_small_where_the_model_fits_and_reaches_a_bump(template, shape_model, tissue_atlas,
                                                                          monkeypatch):
    """A subject made by the model itself (alpha = (1, -0.8), registered from that alpha): the
    residual moves the surface by a third of a voxel at most on average (measured 0.64 mm mean
    along the normal, inwards everywhere: the atlas's Gaussians project a slightly fuller bone
    than a sharp-edged one, and the registration, whose densities are fixed, shrinks it; see
    docs/methods.md), and nowhere outwards at the bump's place; the same bone with a 3 mm bump the
    model cannot make: the residual moves the surface outwards onto it (measured 1.17 mm along the
    normal within 5 mm of its top)."""
    near = np.linalg.norm(template.vertices - BUMP_CENTRE, axis=1) < 5.0
    fits, fits_n = _residual_after_registration(template, shape_model, tissue_atlas,
                                                _scan(template, alpha=(1.0, -0.8), shape_model=shape_model),
                                                (1.0, -0.8), monkeypatch)
    bump, bump_n = _residual_after_registration(template, shape_model, tissue_atlas, _bump_scan(template),
                                                (0.0, 0.0), monkeypatch)
    assert np.abs(fits_n).mean() < 0.7 and np.linalg.norm(fits, axis=1).max() < 2.0  # 2 mm voxels
    assert fits_n[near].mean() < 0.0
    assert bump_n[near].mean() > 0.8 and bump[near, 0].mean() > 0.8  # outwards (+x) onto the 3 mm bump
    assert bump_n[near].mean() > np.abs(bump_n[~near]).mean() + 0.4  # more there than elsewhere


def test_a_run_with_the_residual_writes_it_into_its_surface_report_and_checkpoint(template, shape_model,
                                                                                   tissue_atlas, tmp_path):
    """residual=on end to end: the written model surface is the template carried by the model and
    the residual (their split in alpha.json adds up to it); a resumed run continues bit for bit."""
    import trimesh

    from clgs.methods.shape_guided import reconstruct_shape_guided, surface_displacement_parts

    scan = _bump_scan(template)
    parts = AnatomyParts(template, shape_model, tissue_atlas)
    kw = _small(alpha_freeze=3, alpha_init_iterations=10, residual="on", residual_init_iterations=20,
                residual_points=12, lambda_residual=1e-3)
    kw.pop("checkpoint_every")
    full = reconstruct_shape_guided(scan, parts, tmp_path / "a", iterations=24, checkpoint_every=12, **kw)
    reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=12, checkpoint_every=12,
                             schedule_iterations=24, **kw)
    resumed = reconstruct_shape_guided(scan, parts, tmp_path / "b", iterations=24, resume=True, progress=False)
    np.testing.assert_array_equal(full.volume, resumed.volume)
    np.testing.assert_array_equal(full.trainer.sets[0].params["residual"].detach(),
                                  resumed.trainer.sets[0].params["residual"].detach())
    split = json.loads((tmp_path / "a" / "alpha.json").read_text())["displacement"]
    assert split["residual"] == "on" and split["residual_max_mm"] > 0.1
    assert 0 < split["residual_share"] < 1 and split["residual_normal_mean_mm"] <= split["residual_mean_mm"]
    p = surface_displacement_parts(template, full.trainer.sets[0])
    np.testing.assert_allclose(p["vertices"], template.vertices + p["model_mm"] + p["residual_mm"], atol=1e-9)
    # what a user opens: the STL (LPS-tagged, float32, three corners per face) read by trimesh
    raw = trimesh.load(tmp_path / "a" / "shape_surface.stl", process=False)
    np.testing.assert_allclose(raw.vertices * [-1, -1, 1], p["vertices"][np.asarray(template.faces)].reshape(-1, 3),
                               atol=1e-4)
    assert np.abs(p["residual_mm"]).max() > 0.05  # so the file differs from the model's surface
    assert full.displacement == split

