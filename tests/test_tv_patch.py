"""The fused TV patch (clgs.fit.tv_patch, cl/voxelizer.cl patch_* kernels) against tv3d of the voxelizer's
field (the unfused path), the plain torch reference, finite differences, and itself."""
import pytest
import torch
from test_voxelizer import scene as voxelizer_scene

import clgs.fit.tv_patch as tp
from clgs.fit import losses as L
from clgs.fit.tv_patch import patch_field, patch_tv, tv_patch
from clgs.geometry import Grid
from clgs.ops.voxelizer import cov_prec, voxelize_precision
from clgs.reference import voxelization as ref

GRID = Grid((40, 37, 45), (-0.98, -0.96, -0.99), (0.05, 0.052, 0.045))
NEEDS = ("means", "prec", "densities")


def scene(n, dtype=torch.float32, seed=0, spread=1.1, log_scale=(-3.6, -2.6)):
    """n Gaussians over GRID (some partly or wholly outside), boxes a few voxels wide."""
    return voxelizer_scene(n, dtype, seed, spread, log_scale)


def matrices(params):
    """(means, prec, densities, extent) as leaves (extent without gradient)."""
    means, scales, quats, rho = params
    _, prec, extent = cov_prec(scales, quats, cov=False, extent=True)
    return [means.detach().clone().requires_grad_(), prec.detach().clone().requires_grad_(),
            rho.detach().clone().requires_grad_(), extent.detach()]


def unfused(m, p, r, e, grid):
    return L.tv3d(voxelize_precision(m, p, r, e, grid))


BLOCKS = {
    "interior 16^3": ((10, 9, 12), (16, 16, 16)),
    "edge, clipped 7x16x5": ((33, 0, 40), (7, 16, 5)),  # at the volume's far x and z faces, near y = 0
    "flat 1x12x20": ((5, 6, 7), (1, 12, 20)),
    "line 9x1x1": ((3, 4, 5), (9, 1, 1)),
}


@pytest.mark.parametrize("name", sorted(BLOCKS))
def test_matches_the_unfused_path_float32(name):
    """Field bitwise; TV and gradients (upstream weight 0.05, as trained) to float32 rounding: the
    TV's sums and its gradient's three terms per sample are added in another order (one ulp)."""
    start, size = BLOCKS[name]
    block = GRID.block(start, size)
    a, b = matrices(scene(3000)), matrices(scene(3000))
    assert torch.equal(patch_field(*a, block), voxelize_precision(*[t.detach() for t in a], block))
    got, expected = tv_patch(*a, block), unfused(*b, block)
    assert got.dtype == torch.float32 and got.shape == ()
    assert float(expected.detach()) > 0
    torch.testing.assert_close(got, expected, rtol=2e-6, atol=0)
    (0.05 * got).backward()
    (0.05 * expected).backward()
    for n, x, y in zip(NEEDS, a, b):
        peak = float(y.grad.abs().max())
        assert peak > 0, n
        torch.testing.assert_close(x.grad, y.grad, rtol=1e-5, atol=1e-6 * peak, msg=n)
        # exactly the Gaussians the unfused path touches get a gradient
        assert torch.equal(x.grad.reshape(len(x), -1).any(1), y.grad.reshape(len(y), -1).any(1)), n


def test_matches_the_torch_reference_float64():
    """float64 build against tv3d of the plain torch voxelizer, values and autograd gradients to
    scales, quaternions, means and densities."""
    params = [p.requires_grad_() for p in scene(250, dtype=torch.float64, seed=2)]
    block = GRID.block((6, 7, 8), (13, 12, 14))
    _, prec, extent = cov_prec(params[1], params[2], cov=False, extent=True)
    got = tv_patch(params[0], prec, params[3], extent, block)
    expected = L.tv3d(ref.voxelize(*params, block))
    assert got.dtype == torch.float64 and float(expected.detach()) > 0
    torch.testing.assert_close(got, expected, rtol=1e-11, atol=0)
    for x, y in zip(torch.autograd.grad(got, params), torch.autograd.grad(expected, params)):
        assert float(y.abs().max()) > 0
        torch.testing.assert_close(x, y, rtol=1e-8, atol=1e-10 * float(y.abs().max()))


def test_gradcheck_float64():
    params = scene(6, dtype=torch.float64, seed=3, spread=0.25, log_scale=(-2.2, -1.6))
    m, p, r, e = matrices(params)
    block = Grid((7, 6, 9), (-0.4, -0.38, -0.42), (0.1, 0.11, 0.095))
    assert float(tv_patch(m, p, r, e, block).detach()) > 0.01
    assert torch.autograd.gradcheck(lambda a, b, c: tv_patch(a, b, c, e, block), (m, p, r),
                                    eps=1e-7, atol=1e-6, rtol=1e-4)


def test_same_bits_every_run():
    block = GRID.block((20, 3, 11), (16, 16, 16))
    outs = []
    for _ in range(2):
        a = matrices(scene(4000, seed=4))
        v = tv_patch(*a, block)
        v.backward()
        outs.append([v.detach(), *(t.grad for t in a[:3])])
    for x, y in zip(*outs):
        assert torch.equal(x, y)


def test_no_gaussians_or_none_reaching_the_patch():
    block = GRID.block((0, 0, 0), (8, 8, 8))
    empty = [torch.zeros(0, 3, requires_grad=True), torch.zeros(0, 6, requires_grad=True),
             torch.zeros(0, requires_grad=True), torch.zeros(0, 3)]
    v = tv_patch(*empty, block)
    assert float(v.detach()) == 0
    v.backward()
    assert empty[0].grad.shape == (0, 3)
    far = matrices(scene(50, seed=5))
    with torch.no_grad():
        far[0] += 10.0  # every box far from the grid
    v = tv_patch(*far, block)
    assert float(v.detach()) == 0
    v.backward()
    assert not far[0].grad.any() and not far[1].grad.any() and not far[2].grad.any()


def test_single_sample_patch_has_zero_tv_and_a_zero_gradient():
    a = matrices(scene(200, seed=6))
    one = GRID.block((20, 18, 22), (1, 1, 1))
    v = tv_patch(*a, one)
    assert float(v.detach()) == 0
    v.backward()
    assert not a[0].grad.any()


def test_one_gaussian_covering_everything_and_list_regrowth(monkeypatch):
    """A very wide Gaussian is in every brick's list (among many small ones); with a deliberately
    tiny list capacity the first run overflows, is detected, and repeats with room: same result."""
    params = scene(1500, seed=7)
    params[0][0] = torch.tensor([0.0, 0.0, 0.0])
    params[1][0] = torch.tensor([1.5, 1.2, 1.8])
    params[3][0] = 0.5
    block = GRID.block((8, 8, 8), (24, 24, 24))
    a, b = matrices(params), matrices(params)
    expected = unfused(*b, block)
    runner = tp._runner(None)
    monkeypatch.setattr(runner, "_cap_list", 64)
    got = tv_patch(*a, block)
    assert runner._cap_list > 64
    torch.testing.assert_close(got, expected, rtol=2e-6, atol=0)
    got.backward()
    expected.backward()
    for n, x, y in zip(NEEDS, a, b):
        torch.testing.assert_close(x.grad, y.grad, rtol=1e-5, atol=1e-6 * float(y.grad.abs().max()), msg=n)
    assert a[0].grad[0].abs().max() > 0  # the wide one moves too


def test_only_requested_gradients_and_no_grad():
    block = GRID.block((5, 5, 5), (12, 12, 12))
    params = scene(800, seed=8)
    full = matrices(params)
    tv_patch(*full, block).backward()
    for k in range(3):
        part = [t.detach().clone().requires_grad_(i == k) for i, t in enumerate(matrices(params)[:3])]
        tv_patch(*part, full[3], block).backward()
        for i, t in enumerate(part):
            if i == k:
                assert torch.equal(t.grad, full[k].grad)
            else:
                assert t.grad is None
    with torch.no_grad():
        v = tv_patch(*full, block)
    assert not v.requires_grad and float(v) > 0


def test_large_grids_go_through_the_unfused_path():
    a, b = matrices(scene(600, seed=9)), matrices(scene(600, seed=9))
    got, expected = tv_patch(*a, GRID), unfused(*b, GRID)  # 6 x 5 x 5 = 150 bricks: fused
    torch.testing.assert_close(got, expected, rtol=2e-6, atol=0)
    big = Grid((72, 72, 80), (-1.0, -1.0, -1.0), (0.028, 0.028, 0.025))  # 10 x 9 x 9 bricks > 512
    torch.testing.assert_close(tv_patch(*a, big), unfused(*b, big), rtol=0, atol=0)


def test_bad_inputs_are_clear_errors():
    m, p, r, e = matrices(scene(10))
    block = GRID.block((0, 0, 0), (4, 4, 4))
    with pytest.raises(ValueError, match="prec"):
        tv_patch(m, p[:, :3], r, e, block)
    with pytest.raises(TypeError, match="dtype"):
        tv_patch(m.double(), p, r, e, block)
    with pytest.raises(TypeError, match="Grid"):
        tv_patch(m, p, r, e, (4, 4, 4))


def test_loss_term_entry_on_both_backends():
    """patch_tv: the OpenCL backend with the projection's kept matrices, without them, and the
    torch backend (tv3d of its voxelizer) give the same TV and gradients (float64)."""
    from clgs.fit.trainer import Backend

    params = [p.requires_grad_() for p in scene(300, dtype=torch.float64, seed=10)]
    block = GRID.block((10, 12, 14), (10, 9, 11))
    cl = Backend("cl")
    cl._matrices(params[1], params[2])  # what the step's projection leaves behind
    assert cl._kept(params[1], params[2]) is not None
    results = []
    for backend, _keep in ((cl, True), (Backend("cl"), False), (Backend("torch"), False)):
        v = patch_tv(backend, params, block)
        results.append([v.detach(), *torch.autograd.grad(v, params)])
    assert float(results[0][0]) > 0
    for other in results[1:]:
        for x, y in zip(results[0], other):
            torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-12 * float(y.abs().max()))
