"""cl/field_sampler.cl against torch's grid_sample (border padding, align_corners=True), finite
differences in float64, bits, degenerate input; and the deformation built on it."""
import pytest
import torch
import torch.nn.functional as F

from clgs.ops.field_sampler import FieldSampler, sample
from clgs.shape.model import exp_velocity, sample_field


def reference(field, pts):
    """torch's grid_sample with the same conventions: pts (3, P) voxel units x, y, z."""
    C, Z, Y, X = field.shape
    n = torch.tensor([X - 1, Y - 1, Z - 1], dtype=field.dtype)[:, None]
    g = (pts / n * 2 - 1).T.reshape(1, 1, 1, -1, 3)
    out = F.grid_sample(field[None], g, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(C, -1)


def scene(C=3, shape=(6, 5, 7), P=203, dtype=torch.float64, margin=1.5, seed=0):
    g = torch.Generator().manual_seed(seed)
    field = torch.randn((C, *shape), generator=g, dtype=dtype)
    Z, Y, X = shape
    hi = torch.tensor([X - 1, Y - 1, Z - 1], dtype=dtype)[:, None]
    pts = torch.rand((3, P), generator=g, dtype=dtype) * (hi + 2 * margin) - margin  # some outside
    return field, pts


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("C,shape", [(3, (6, 5, 7)), (1, (2, 9, 3)), (4, (5, 2, 2))])
def test_values_and_gradients_match_grid_sample(dtype, tol, C, shape):
    field, pts = scene(C, shape, dtype=dtype)
    field.requires_grad_(True)
    pts.requires_grad_(True)
    ours, ref = sample(field, pts), reference(field, pts)
    assert ours.shape == (C, pts.shape[1])
    assert torch.allclose(ours, ref, atol=tol, rtol=0)
    up = torch.randn_like(ref)
    g_ours = torch.autograd.grad(ours, (field, pts), up)
    g_ref = torch.autograd.grad(ref, (field, pts), up)
    scale = float(up.abs().max() * field.detach().abs().max())
    assert torch.allclose(g_ours[0], g_ref[0], atol=tol * 10 * scale, rtol=0)
    assert torch.allclose(g_ours[1], g_ref[1], atol=tol * 10 * scale, rtol=0)


def test_finite_differences_float64():
    field, pts = scene(P=40, margin=0.0, seed=3)
    # keep points off the cell faces, where the map has kinks
    pts = torch.floor(pts) + 0.1 + 0.8 * (pts - torch.floor(pts))
    pts = torch.minimum(pts, torch.tensor([5.9, 3.9, 4.9], dtype=pts.dtype)[:, None])
    field.requires_grad_(True)
    pts.requires_grad_(True)
    assert torch.autograd.gradcheck(sample, (field, pts), eps=1e-6, atol=1e-7, rtol=1e-6)


def test_border_has_zero_point_gradient_and_clamped_values():
    field, _ = scene(C=1, shape=(4, 4, 4))
    pts = torch.tensor([[-3.0, 3.0, 7.5, 1.5], [1.5, 1.5, 1.5, -0.5], [1.5, 1.5, 1.5, 1.5]],
                       dtype=field.dtype, requires_grad=True)
    out = sample(field, pts)
    inside = pts.detach().clone()
    inside[0] = inside[0].clamp(0, 3)
    inside[1] = inside[1].clamp(0, 3)
    assert torch.allclose(out, reference(field, inside), atol=1e-12)
    (g,) = torch.autograd.grad(out.sum(), pts)
    assert g[0, 0] == 0 and g[0, 1] == 0 and g[0, 2] == 0  # beyond, on and beyond the x border
    assert g[1, 3] == 0 and g[0, 3] != 0  # y clamped, x inside


def test_same_input_same_bits_and_gpu_configuration():
    field, pts = scene(P=5000, dtype=torch.float32, seed=5)
    field.requires_grad_(True)
    up = torch.randn(3, 5000, generator=torch.Generator().manual_seed(1))

    def run(sampler):
        out = sample(field, pts.clone().requires_grad_(True), sampler)
        return [out] + list(torch.autograd.grad(out, field, up))

    a, b = run(FieldSampler()), run(FieldSampler())
    gpu = FieldSampler()
    gpu.io.host_memory = False  # device buffers filled and read back by copies, as on a GPU
    c = run(gpu)
    for x, y, z in zip(a, b, c):
        assert torch.equal(x, y) and torch.equal(x, z)


def test_nan_points_give_finite_values_and_no_gradient():
    field, pts = scene(P=16)
    pts[:, 3] = float("nan")
    pts.requires_grad_(True)
    field.requires_grad_(True)
    out = sample(field, pts)
    assert torch.isfinite(out).all()
    gf, gp = torch.autograd.grad(out.sum(), (field, pts))
    assert torch.isfinite(gf).all() and torch.isfinite(gp).all() and (gp[:, 3] == 0).all()


def test_empty_points_and_bad_input():
    field, _ = scene()
    assert sample(field, torch.zeros((3, 0), dtype=field.dtype)).shape == (3, 0)
    pts = torch.zeros((3, 4), dtype=field.dtype)
    with pytest.raises(ValueError, match=r"\(C, Z, Y, X\) with 1 <= C <= 4"):
        sample(torch.zeros((5, 3, 3, 3), dtype=field.dtype), pts)
    with pytest.raises(ValueError, match="at least 2 voxels"):
        sample(torch.zeros((3, 1, 3, 3), dtype=field.dtype), pts)
    with pytest.raises(ValueError, match=r"points must be \(3, P\)"):
        sample(field, pts.T)
    with pytest.raises(ValueError, match="share a float32 or float64 dtype"):
        sample(field, pts.float())


def test_deformation_in_opencl_matches_the_torch_one():
    """exp(v) by scaling and squaring and the field at points: OpenCL (voxel units) and torch
    (normalised units) agree to rounding, values and gradients wrt v."""
    g = torch.Generator().manual_seed(2)
    spacing = (4.0, 3.0, 5.0)  # z, y, x mm
    smooth = F.avg_pool3d(torch.randn((3, 12, 10, 9), generator=g, dtype=torch.float64)[None], 3, 1, 1)[0]
    v = (smooth * 30.0).requires_grad_(True)  # up to a few cells: several squarings
    pts = torch.rand((50, 3), generator=g, dtype=torch.float64) * torch.tensor([40.0, 27.0, 44.0])
    origin = (0.0, 0.0, 0.0)
    sampler = FieldSampler()
    results = []
    for s in (None, sampler):
        u = exp_velocity(v, spacing, sampler=s)
        at = sample_field(u, pts, spacing, origin, sampler=s)
        (gv,) = torch.autograd.grad((u * u).sum() + at.sum(), v)
        results.append((u, at, gv))
    (u0, a0, g0), (u1, a1, g1) = results
    assert float(u0.detach().abs().max()) > 3.0  # the test deforms by more than a cell
    assert torch.allclose(u0, u1, atol=1e-10)
    assert torch.allclose(a0, a1, atol=1e-10)
    assert torch.allclose(g0, g1, atol=1e-8 * float(g0.abs().max()))
