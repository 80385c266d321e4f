"""Gaussian voxelizer (cl/voxelizer.cl) against the plain torch reference, finite differences,
and itself (blocks vs full grid, points vs grid, float32 vs float64, run vs run)."""
import pytest
import torch

from clgs.geometry import Grid
from clgs.ops.voxelizer import Voxelizer, voxelize, voxelize_points, voxelize_precision
from clgs.reference import voxelization as ref
from clgs.reference.gaussians import axis_extent, precision

GRID = Grid((17, 19, 23), (-0.93, -0.97, -1.01), (0.085, 0.1, 0.09))


def scene(n, dtype=torch.float32, seed=0, spread=1.2, log_scale=(-3.5, -1.5)):
    """n Gaussians, some of them partly or wholly outside GRID."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * spread
    lo, hi = log_scale
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64))
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    rho = torch.rand(n, generator=g, dtype=torch.float64) + 0.1
    return [t.to(dtype) for t in (means, scales, quats, rho)]


def assert_close32(out, expected):
    """float32 agreement: 1e-5 relative, with an absolute floor of 1e-6 of the peak."""
    expected = expected.detach()
    peak = float(expected.abs().max())
    assert peak > 0, "the test scene must produce a non-zero field"
    torch.testing.assert_close(out.detach(), expected, rtol=1e-5, atol=1e-6 * peak)


def test_grid_matches_reference():
    params = scene(1500)  # several binning chunks
    out = voxelize(*params, GRID)
    assert out.shape == GRID.shape and out.dtype == torch.float32
    expected = ref.voxelize(*params, GRID)
    assert_close32(out, expected)
    assert (expected > 0).float().mean() > 0.5  # the scene covers most of the grid


def test_fast_references_match_the_dense_reference():
    params = scene(300, dtype=torch.float64)
    torch.testing.assert_close(ref.voxelize_windowed(*params, GRID), ref.voxelize(*params, GRID),
                               rtol=1e-12, atol=1e-12)
    pts = torch.rand(2000, 3, generator=torch.Generator().manual_seed(13), dtype=torch.float64) * 2.4 - 1.2
    expected = ref.voxelize_points(*params, pts)
    assert expected.max() > 0
    torch.testing.assert_close(ref.voxelize_points_kdtree(*params, pts), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("start, size", [((0, 0, 0), (17, 19, 23)), ((3, 5, 7), (8, 9, 10)), ((16, 18, 22), (1, 1, 1)),
                                         ((1, 0, 13), (16, 19, 10)), ((4, 2, 1), (5, 17, 3))])
def test_block_equals_the_same_region_of_the_full_grid_bitwise(start, size):
    params = scene(800)
    full = voxelize(*params, GRID)
    block = voxelize(*params, GRID.block(start, size))
    (z, y, x), (dz, dy, dx) = start, size
    assert torch.equal(block, full[z:z + dz, y:y + dy, x:x + dx])


def test_brick_shape_variants_give_the_same_bits():
    params = scene(600)
    a = voxelize(*params, GRID)
    b = voxelize(*params, GRID, voxelizer=Voxelizer(brick=(4, 2)))
    assert torch.equal(a, b)


def test_points_equal_grid_values_at_grid_points():
    params = scene(700)
    full = voxelize(*params, GRID)
    pts = torch.from_numpy(GRID.points().reshape(-1, 3)).float()
    perm = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(1))
    out = voxelize_points(*params, pts[perm])
    assert_close32(out, full.reshape(-1)[perm])


def test_points_match_reference():
    params = scene(900)
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(3000, 3, generator=g) * 2.6 - 1.3  # some outside every box
    pts[:200] = params[0][:200] + 0.01 * torch.randn(200, 3, generator=g)  # some at the centres
    out = voxelize_points(*params, pts)
    assert out.shape == (3000,)
    assert_close32(out, ref.voxelize_points(*params, pts))
    # a single point, and points given as a NumPy array
    one = voxelize_points(*params, pts[7:8].numpy())
    assert_close32(one, ref.voxelize_points(*params, pts[7:8]))


def _requires_grad(params):
    return [p.detach().clone().requires_grad_() for p in params]


def test_gradcheck_grid_block_points():
    params = _requires_grad(scene(5, dtype=torch.float64, spread=0.6, log_scale=(-2.0, -1.0)))
    grid = Grid((6, 7, 9), (-0.8, -0.75, -0.85), (0.27, 0.25, 0.2))
    block = grid.block((1, 2, 3), (4, 5, 4))
    pts = torch.rand(30, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 1.6 - 0.8
    kw = dict(eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    assert voxelize(*params, grid).abs().max() > 0.05
    assert torch.autograd.gradcheck(lambda *a: voxelize(*a, grid), params, **kw)
    assert torch.autograd.gradcheck(lambda *a: voxelize(*a, block), params, **kw)
    assert torch.autograd.gradcheck(lambda *a: voxelize_points(*a, pts), params, **kw)


@pytest.mark.parametrize("where", ["grid", "block", "points"])
def test_gradients_match_reference_autograd(where):
    params = _requires_grad(scene(400, dtype=torch.float64))
    pts = torch.rand(2000, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 2.2 - 1.1
    grid = GRID.block((2, 3, 4), (9, 11, 13)) if where == "block" else GRID
    if where == "points":
        run, run_ref = (lambda *a: voxelize_points(*a, pts)), (lambda *a: ref.voxelize_points(*a, pts))
    else:
        run, run_ref = (lambda *a: voxelize(*a, grid)), (lambda *a: ref.voxelize(*a, grid))
    out = run(*params)
    w = torch.randn(out.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    got = torch.autograd.grad((run(*params) * w).sum(), params)
    expected = torch.autograd.grad((run_ref(*params) * w).sum(), params)
    for name, a, b in zip(("means", "scales", "quats", "densities"), got, expected):
        assert b.abs().max() > 0, name
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()), msg=name)


def test_only_requested_gradients_are_computed_and_they_agree():
    params = scene(300, dtype=torch.float64)
    w = torch.randn(GRID.shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    full = _requires_grad(params)
    all_grads = torch.autograd.grad((voxelize(*full, GRID) * w).sum(), full)
    for k in range(4):
        part = [p.detach().clone().requires_grad_(i == k) for i, p in enumerate(params)]
        (voxelize(*part, GRID) * w).sum().backward()
        for i, p in enumerate(part):
            if i == k:
                torch.testing.assert_close(p.grad, all_grads[k], rtol=1e-12, atol=1e-14)
            else:
                assert p.grad is None


def test_float32_agrees_with_float64():
    p64 = _requires_grad(scene(500, dtype=torch.float64))
    p32 = _requires_grad([p.detach().float() for p in p64])
    w = torch.randn(GRID.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    o64, o32 = voxelize(*p64, GRID), voxelize(*p32, GRID)
    assert o32.dtype == torch.float32 and o64.dtype == torch.float64
    # the float32 cut can differ from the float64 one only for samples within rounding of a box
    # face, where a Gaussian is at most exp(-4.5) of its peak: compare where both agree on support
    diff = (o32.double() - o64).abs()
    assert float((diff < 1e-5 * float(o64.detach().max())).double().mean()) > 0.999
    g64 = torch.autograd.grad((o64 * w).sum(), p64)
    g32 = torch.autograd.grad((o32 * w.float()).sum(), p32)
    for a, b in zip(g32, g64):
        rel = (a.double() - b).norm() / b.norm()
        assert rel < 1e-3


def test_same_bits_every_run():
    params = _requires_grad(scene(2000, seed=8))
    pts = torch.rand(4000, 3, generator=torch.Generator().manual_seed(9)) * 2 - 1
    w = torch.randn(GRID.shape, generator=torch.Generator().manual_seed(10))
    wp = torch.randn(4000, generator=torch.Generator().manual_seed(11))

    def run():
        out = voxelize(*params, GRID)
        outp = voxelize_points(*params, pts)
        grads = torch.autograd.grad((out * w).sum() + (outp * wp).sum(), params)
        return [out, outp, *grads]

    first, second = run(), run()
    for a, b in zip(first, second):
        assert torch.equal(a, b)


EXTREMES = {
    "tiny scales": dict(scales=1e-4),
    "unit scales": dict(scales=1.0),
    "needles": dict(scales=(0.3, 3e-4, 3e-4)),
    "pancakes": dict(scales=(0.3, 0.3, 3e-4)),
    "tiny densities": dict(rho=1e-8),
    "huge densities": dict(rho=1e4),
    "zero densities": dict(rho=0.0),
    "all outside": dict(shift=5.0),
}


@pytest.mark.parametrize("case", sorted(EXTREMES))
def test_extreme_inputs_are_finite_and_right(case):
    spec = EXTREMES[case]
    means, scales, quats, rho = scene(60, dtype=torch.float64, seed=12)
    if "scales" in spec:
        scales = torch.ones_like(scales) * torch.tensor(spec["scales"], dtype=torch.float64)
    if "rho" in spec:
        rho = torch.full_like(rho, spec["rho"])
    means = means + spec.get("shift", 0.0)
    for dtype in (torch.float32, torch.float64):
        params = _requires_grad([t.to(dtype) for t in (means, scales, quats, rho)])
        pts = torch.from_numpy(GRID.points()[::4, ::4, ::4].reshape(-1, 3)).to(dtype)
        out, outp = voxelize(*params, GRID), voxelize_points(*params, pts)
        assert torch.isfinite(out).all() and torch.isfinite(outp).all()
        grads = torch.autograd.grad(out.sum() + outp.sum(), params, allow_unused=False)
        assert all(torch.isfinite(g).all() for g in grads)
        if dtype == torch.float64:
            expected = ref.voxelize(*[p.detach() for p in params], GRID)
            torch.testing.assert_close(out.detach(), expected, rtol=1e-9, atol=1e-9 * float(expected.abs().max()))
        elif case in ("needles", "pancakes"):
            # thin Gaussians: d^T P d cancels in float32 (P holds 1/s^2 ~ 1e7 next to ~10), for the
            # kernels and the float32 reference alike; the kernel stays within 2% of the peak of
            # the float64 truth (the float32 reference is about 2x further off)
            truth = ref.voxelize(means, scales, quats, rho, GRID)
            torch.testing.assert_close(out.detach().double(), truth, rtol=0, atol=0.02 * float(truth.max()) + 1e-12)
        else:
            assert_close32(out, ref.voxelize(*[p.detach() for p in params], GRID)) if out.any() else None
        # at the Gaussians' own centres every case has a field (unless all densities are zero)
        centres = params[0].detach()
        at_centres = voxelize_points(*params, centres)
        expected_c = ref.voxelize_points(*[p.detach() for p in params], centres)
        assert torch.isfinite(at_centres).all()
        if case == "zero densities":
            assert not at_centres.any()
        elif dtype == torch.float64 or case not in ("needles", "pancakes"):
            torch.testing.assert_close(at_centres, expected_c, rtol=1e-5 if dtype == torch.float32 else 1e-9,
                                       atol=1e-6 * float(expected_c.abs().max()))
            assert (at_centres >= params[3].detach() * (1 - 1e-6)).all()  # at least their own peak
        if case == "all outside" or case == "zero densities":
            assert not out.any() and not outp.any()


def test_no_gaussians_and_a_single_voxel_grid():
    empty = [torch.zeros(0, 3), torch.ones(0, 3), torch.ones(0, 4), torch.zeros(0)]
    assert torch.equal(voxelize(*empty, GRID), torch.zeros(GRID.shape))
    assert torch.equal(voxelize_points(*empty, torch.zeros(5, 3)), torch.zeros(5))
    params = _requires_grad(scene(50, dtype=torch.float64, spread=0.3, log_scale=(-1.5, -1.0)))
    one = Grid((1, 1, 1), (0.05, -0.02, 0.01), (0.1, 0.1, 0.1))
    out = voxelize(*params, one)
    assert out.shape == (1, 1, 1) and out.item() > 0
    torch.testing.assert_close(out, ref.voxelize(*params, one), rtol=1e-12, atol=0)
    pt = voxelize_points(*params, torch.tensor([[0.05, -0.02, 0.01]], dtype=torch.float64))
    torch.testing.assert_close(pt, out.reshape(1), rtol=1e-12, atol=0)
    assert torch.autograd.gradcheck(lambda *a: voxelize(*a, one), params, eps=1e-6, atol=1e-6, rtol=1e-4,
                                    fast_mode=True)
    assert voxelize_points(*params, torch.zeros(0, 3, dtype=torch.float64)).shape == (0,)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda p: [p[0][:, :2], *p[1:]], "means"),
        (lambda p: [p[0], -p[1], *p[2:]], "scales must be positive"),
        (lambda p: [p[0] * float("nan"), *p[1:]], "finite"),
        (lambda p: [p[0].double(), *p[1:]], "dtype"),
        (lambda p: [p[0].half(), p[1].half(), p[2].half(), p[3].half()], "float32 or float64"),
        (lambda p: [p[0], p[1] * 1e-30, *p[2:]], "scales too small"),
    ],
)
def test_bad_inputs_are_clear_errors(change, message):
    params = change(scene(10))
    with pytest.raises((ValueError, TypeError), match=message):
        voxelize(*params, GRID)


def test_bad_grid_and_points_are_clear_errors():
    params = scene(10)
    with pytest.raises(TypeError, match="Grid"):
        voxelize(*params, (4, 4, 4))
    with pytest.raises(ValueError, match="points must be"):
        voxelize_points(*params, torch.zeros(4, 2))
    with pytest.raises(ValueError, match="finite"):
        voxelize_points(*params, torch.full((4, 3), float("inf")))


def test_precision_entry_point_matches_and_differentiates():
    from clgs.ops.voxelizer import cov_prec

    params = _requires_grad(scene(200, dtype=torch.float64))
    _, prec, extent = cov_prec(params[1], params[2], cov=False, extent=True)  # what voxelize builds
    block = GRID.block((2, 2, 2), (7, 8, 9))
    a = voxelize_precision(params[0], prec, params[3], extent, block)
    assert torch.equal(a, voxelize(*params, block))
    # and the torch formulas give the same field to rounding
    b = voxelize_precision(params[0], precision(params[1], params[2]), params[3], axis_extent(params[1], params[2]),
                           block)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    pts = torch.rand(50, 3, dtype=torch.float64) - 0.5
    assert torch.equal(voxelize_precision(params[0], prec, params[3], extent, pts), voxelize_points(*params, pts))
    g = torch.autograd.grad(a.sum(), params)
    g_ref = torch.autograd.grad(voxelize(*params, block).sum(), params)
    for x, y in zip(g, g_ref):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="prec"):
        voxelize_precision(params[0], prec[:, :3], params[3], extent, block)


def test_grid_candidates_keep_every_gaussian_that_reaches_the_block_and_change_nothing():
    """The culling before packing: every Gaussian with a non-zero value on the block is kept (each
    checked alone), at least one is dropped, and the field and gradients through the culled op
    equal, bitwise, those of the op fed all Gaussians."""
    from clgs.ops.voxelizer import _GridField, default_voxelizer, grid_candidates

    params = _requires_grad(scene(300, dtype=torch.float64))
    prec, extent = precision(params[1], params[2]), axis_extent(params[1], params[2])
    block = GRID.block((3, 5, 7), (6, 5, 4))
    idx = grid_candidates(params[0], extent, block)
    assert idx is not None and 0 < idx.numel() < 300
    assert torch.equal(idx, torch.sort(idx).values)
    kept = set(idx.tolist())
    for i in range(300):
        alone = voxelize_precision(params[0][i:i + 1].detach(), prec[i:i + 1].detach(), params[3][i:i + 1].detach(),
                                   extent[i:i + 1], block)
        if float(alone.abs().max()) > 0:
            assert i in kept
    # the cube bound used by the trainer (3 max(scale)) keeps a superset
    cube = grid_candidates(params[0], params[1].detach().amax(1) * 3.003, block)
    assert kept <= set(cube.tolist())
    culled = voxelize_precision(params[0], prec, params[3], extent, block)
    whole = _GridField.apply(params[0], prec, params[3], extent, block, default_voxelizer())
    assert torch.equal(culled, whole)
    w = torch.rand(block.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    g1 = torch.autograd.grad((culled * w).sum(), params, retain_graph=True)
    g2 = torch.autograd.grad((whole * w).sum(), params)
    for a, b in zip(g1, g2):
        assert torch.equal(a, b)


def test_small_grid_and_binned_paths_give_the_same_bits(monkeypatch):
    """Small grids (a TV patch) are binned by one work-item and their backward runs unsorted; the
    large-grid path (chunked counting sort, sorted backward) must give the very same bits."""
    import clgs.ops.voxelizer as vz

    params = _requires_grad(scene(900, seed=4))
    w = torch.randn(GRID.shape, generator=torch.Generator().manual_seed(5))
    block = GRID.block((2, 3, 4), (11, 12, 13))
    wb = w[2:13, 3:15, 4:17]

    def run():
        out, part = voxelize(*params, GRID), voxelize(*params, block)
        return [out, part, *torch.autograd.grad((out * w).sum() + (part * wb).sum(), params)]

    small = run()
    monkeypatch.setattr(vz, "SMALL_CELLS", 0)
    monkeypatch.setattr(vz, "_UNSORTED_BYTES", 0)
    binned = run()
    assert float(small[0].detach().abs().max()) > 0 and all(float(g.abs().max()) > 0 for g in small[2:])
    for a, b in zip(small, binned):
        assert torch.equal(a, b)


def test_cov_prec_matches_gaussian_math_and_differentiates():
    """The OpenCL covariance / precision / half-widths kernel against clgs.reference.gaussians (float32,
    N not a multiple of 8 so the last group has idle lanes), gradcheck of its closed-form backward
    (float64) for each output alone and for both together."""
    from clgs.ops.voxelizer import cov_prec
    from clgs.reference.gaussians import covariance

    _, scales, quats, _ = scene(1003, seed=6)
    quats[5] *= 1e-3  # any norm
    cov, prec, ext = cov_prec(scales, quats, extent=True)
    for out, expected in ((cov, covariance(scales, quats)), (prec, precision(scales, quats)),
                          (ext, axis_extent(scales, quats))):
        assert out.shape == expected.shape and out.dtype == torch.float32
        torch.testing.assert_close(out, expected, rtol=2e-5, atol=1e-6 * float(expected.abs().max()))
    assert cov_prec(scales, quats, cov=False, prec=False) == (None, None, None)
    _, s, q, _ = scene(13, dtype=torch.float64, seed=7, log_scale=(-1.5, -0.5))
    s, q = s.requires_grad_(True), q.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: cov_prec(a, b)[:2], (s, q))
    assert torch.autograd.gradcheck(lambda a, b: cov_prec(a, b, cov=False)[1], (s, q))
    assert torch.autograd.gradcheck(lambda a, b: cov_prec(a, b, prec=False, extent=True)[0], (s, q))
    # and against autograd through the torch formulas, with a gradient on each output
    g1, g2 = torch.randn(13, 6, dtype=torch.float64), torch.randn(13, 6, dtype=torch.float64)
    c, p, _ = cov_prec(s, q)
    got = torch.autograd.grad((c * g1).sum() + (p * g2).sum(), (s, q))
    want = torch.autograd.grad((covariance(s, q) * g1).sum() + (precision(s, q) * g2).sum(), (s, q))
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_cov_prec_degenerate_inputs():
    """A zero quaternion gives finite matrices (the identity rotation's limit is not defined, but
    nothing becomes NaN), no Gaussians give empty outputs, bad shapes are clear errors."""
    from clgs.ops.voxelizer import cov_prec

    s = torch.full((3, 3), 0.1, requires_grad=True)
    q = torch.tensor([[0.0, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 2]], requires_grad=True)
    c, p, e = cov_prec(s, q, extent=True)
    assert torch.isfinite(c).all() and torch.isfinite(p).all() and torch.isfinite(e).all()
    torch.testing.assert_close(c[1], torch.tensor([0.01, 0, 0, 0.01, 0, 0.01]))
    gs, gq = torch.autograd.grad(c.sum() + p.sum(), (s, q))
    assert torch.isfinite(gs).all() and torch.isfinite(gq).all()
    c0, p0, e0 = cov_prec(torch.zeros(0, 3), torch.zeros(0, 4), extent=True)
    assert c0.shape == (0, 6) and p0.shape == (0, 6) and e0.shape == (0, 3)
    with pytest.raises(ValueError, match="quats"):
        cov_prec(torch.ones(4, 3), torch.ones(4, 3))


def test_gpu_configuration_gives_the_same_bits():
    """The voxelizer as on a GPU (inputs copied to device buffers, outputs copied back, not
    wrapped host memory), run here: grid, points and their gradients, and the fused TV patch,
    bit for bit as the CPU configuration."""
    from clgs.fit.tv_patch import tv_patch
    from clgs.ops.voxelizer import cov_prec

    gpu = Voxelizer()
    gpu.io.host_memory = False
    pts = torch.rand(700, 3, generator=torch.Generator().manual_seed(4)) * 2 - 1
    w = torch.randn(GRID.shape, generator=torch.Generator().manual_seed(5))
    block = GRID.block((2, 3, 4), (9, 8, 10))
    results = []
    for vox in (Voxelizer(), gpu):
        params = _requires_grad(scene(900, seed=12))
        out = voxelize(*params, GRID, voxelizer=vox)
        outp = voxelize_points(*params, pts, voxelizer=vox)
        _, prec, extent = cov_prec(params[1], params[2], cov=False, extent=True, voxelizer=vox)
        tv = tv_patch(params[0], prec, params[3], extent, block, voxelizer=vox)
        grads = torch.autograd.grad((out * w).sum() + outp.sum() + tv, params)
        results.append([out, outp, tv, *grads])
    assert float(results[0][2].detach()) > 0
    for a, b in zip(*results):
        assert torch.equal(a, b)
