"""clgs.fit.fixed_points (trilinear sampling at fixed points through a sparse matrix) against
torch's grid_sample, finite differences in float64, bits; and the shape-guided centres built on
it against the grid_sample path."""
import pytest
import torch

from clgs.errors import InputError
from clgs.fit.fixed_points import FixedPointSampler
from tests.test_field_sampler import reference, scene


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("C,shape", [(3, (6, 5, 7)), (1, (2, 9, 3)), (4, (5, 2, 2))])
def test_values_and_field_gradient_match_grid_sample(dtype, tol, C, shape):
    field, pts = scene(C, shape, dtype=dtype)  # some points outside the grid: clamped
    field.requires_grad_(True)
    ours = FixedPointSampler(pts.T, shape, dtype)(field)  # (P, C)
    ref = reference(field, pts).T
    assert ours.shape == (pts.shape[1], C)
    assert torch.allclose(ours, ref, atol=tol * float(field.detach().abs().max()), rtol=0)
    up = torch.randn_like(ref)
    g_ours, = torch.autograd.grad(ours, field, up)
    g_ref, = torch.autograd.grad(ref, field, up)
    scale = float(up.abs().max())
    assert torch.allclose(g_ours, g_ref, atol=tol * 10 * scale, rtol=0)


def test_finite_differences_float64():
    field, pts = scene(P=40, seed=3)
    s = FixedPointSampler(pts.T, field.shape[1:], torch.float64)
    field.requires_grad_(True)
    assert torch.autograd.gradcheck(s, (field,), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_same_bits_every_call():
    field, pts = scene(C=3, shape=(9, 8, 10), P=5000, dtype=torch.float32, seed=5)
    s = FixedPointSampler(pts.T, field.shape[1:])
    field.requires_grad_(True)
    up = torch.randn(5000, 3, generator=torch.Generator().manual_seed(1))
    runs = []
    for _ in range(3):
        out = s(field)
        g, = torch.autograd.grad(out, field, up)
        runs.append((out.detach(), g))
    for out, g in runs[1:]:
        assert torch.equal(out, runs[0][0]) and torch.equal(g, runs[0][1])


def test_grid_points_give_the_field_exactly():
    field, _ = scene(C=2, shape=(3, 4, 5), dtype=torch.float64)
    k, j, i = torch.meshgrid(*(torch.arange(n, dtype=torch.float64) for n in (3, 4, 5)), indexing="ij")
    pts = torch.stack([i, j, k], -1).reshape(-1, 3)
    out = FixedPointSampler(pts, (3, 4, 5), torch.float64)(field)
    assert torch.equal(out.T.reshape(field.shape), field)


def test_bad_input_is_refused():
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        FixedPointSampler(torch.zeros(4, 2), (3, 3, 3))
    with pytest.raises(InputError, match="NaN"):
        FixedPointSampler(torch.tensor([[0.0, float("nan"), 0.0]]), (3, 3, 3))
    with pytest.raises(InputError, match="2 voxels"):
        FixedPointSampler(torch.zeros(4, 3), (3, 1, 3))
    s = FixedPointSampler(torch.zeros(4, 3), (3, 3, 3))
    with pytest.raises(InputError, match="field must be"):
        s(torch.zeros(3, 3, 3, 4))
    with pytest.raises(InputError, match="float32"):
        s(torch.zeros(1, 3, 3, 3, dtype=torch.float64))


def test_shape_guided_centres_match_the_grid_sample_path(monkeypatch):
    from clgs.bench.switches import grid_sample_at_ref_points, grid_sample_centres_mm
    from clgs.shape.gaussian_set import ShapeGuidedSet

    s = _small_set()
    n = len(s)
    g = torch.Generator().manual_seed(0)
    u = s.displacement()
    up = torch.randn(n, 3, generator=g)
    got = s.centres_mm(u)
    g_got, = torch.autograd.grad(got, s.alpha, up)
    with monkeypatch.context() as m:  # the grid_sample path the benchmark compares against
        m.setattr(ShapeGuidedSet, "_at_ref_points", grid_sample_at_ref_points)
        m.setattr(ShapeGuidedSet, "_model_centres_mm", grid_sample_centres_mm)
        ref = s.centres_mm()
        g_ref, = torch.autograd.grad(ref, s.alpha, up)
    assert torch.allclose(got, ref, atol=2e-5, rtol=0)
    assert torch.allclose(g_got, g_ref, atol=1e-4 * float(g_ref.abs().max()), rtol=0)


def _small_set():
    from clgs.geometry import Geometry
    from clgs.shape.gaussian_set import ShapeGuidedSet
    from clgs.shape.model import ShapeModel

    g = torch.Generator().manual_seed(0)
    Z, Y, X = 7, 6, 8
    model = ShapeModel(torch.randn(3, Z, Y, X, generator=g) * 0.3, torch.randn(2, 3, Z, Y, X, generator=g) * 0.1,
                       torch.tensor([1.0, 0.5]), spacing=(2.0, 1.5, 1.0), origin=(-6.0, -4.0, -3.5))
    n = 300
    lo = torch.tensor([-3.5, -4.0, -6.0])
    hi = lo + torch.tensor([(X - 1) * 1.0, (Y - 1) * 1.5, (Z - 1) * 2.0])
    p_ref = lo - 1 + torch.rand(n, 3, generator=g) * (hi - lo + 2)
    geo = Geometry.default(n_views=2, n_voxel=16, n_detector=16, volume_mm=40.0, mode="cone")
    return ShapeGuidedSet(p_ref.numpy(), torch.full((n, 3), 0.05), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                          torch.full((n,), 0.1), shape_model=model, geometry=geo, box=(1.0, 1.0, 1.0),
                          scale_bounds=(0.0005, 0.5), schedules={}, alpha=torch.tensor([0.7, -1.2]))


def _exact(s):
    from clgs.shape.gaussian_set import ShapeGuidedSet

    tol = ShapeGuidedSet.LINEAR_TOL
    ShapeGuidedSet.LINEAR_TOL = None
    try:
        return s.centres_mm()
    finally:
        ShapeGuidedSet.LINEAR_TOL = tol


def test_linearised_centres_stay_near_the_exact_map_and_refresh():
    from clgs.shape.gaussian_set import ShapeGuidedSet

    s = _small_set()
    tol = ShapeGuidedSet.LINEAR_TOL
    up = torch.randn(len(s), 3, generator=torch.Generator().manual_seed(2))
    a0 = s.alpha.detach().clone()
    lin = s.centres_mm()  # linearised at a0
    u0 = s.displacement().detach()
    assert s._linear is not None and torch.equal(s._linear[0], a0)
    assert torch.allclose(lin, _exact(s), atol=1e-5, rtol=0)  # at a0 itself: the exact map to rounding
    for d in ([0.4, -0.9], [-0.97, 0.97], [0.9, 0.95]):
        with torch.no_grad():
            s.alpha.copy_(a0 + tol * torch.tensor(d))  # small steps inside the box: no refresh
        lin = s.centres_mm()
        u_lin = s.last_u
        assert torch.equal(s._linear[0], a0)
        g_lin, = torch.autograd.grad(lin, s.alpha, up)
        ex = _exact(s)
        g_ex, = torch.autograd.grad(ex, s.alpha, up)
        moved = float((ex - _exact_at(s, a0)).abs().max().detach())
        err = float((lin - ex).abs().max().detach())
        assert moved > 1e-3 and err < 0.02 * moved  # the linear model follows the map it moved
        # the secant against the exact map's tangent: that map is piecewise trilinear (its
        # derivative jumps at cell faces), and this random field is rougher than a model's
        assert torch.allclose(g_lin, g_ex, atol=0.1 * float(g_ex.abs().max()), rtol=0)
        u_ex = s.displacement().detach()
        assert float((u_lin - u_ex).abs().max()) < 0.02 * float((u_ex - u0).abs().max())
    with torch.no_grad():
        s.alpha.copy_(a0 + 1.1 * tol)  # a step out of the box, small from the last: refreshed there
    s.centres_mm()
    assert torch.equal(s._linear[0], s.alpha.detach())


def _exact_at(s, a):
    keep = s.alpha.detach().clone()
    with torch.no_grad():
        s.alpha.copy_(a)
    try:
        return _exact(s).detach()
    finally:
        with torch.no_grad():
            s.alpha.copy_(keep)


def test_fast_moving_alpha_takes_the_exact_path():
    from clgs.shape.gaussian_set import ShapeGuidedSet

    s = _small_set()
    s.centres_mm()
    with torch.no_grad():
        s.alpha.add_(4 * ShapeGuidedSet.LINEAR_TOL)  # a large step: no new linearisation
    got = s.centres_mm()
    assert s._linear is None
    assert torch.allclose(got, _exact(s), atol=0, rtol=0)
