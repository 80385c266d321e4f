"""The OpenCL L1 + D-SSIM (clgs.ops.ssim) against the torch reference (clgs.fit.losses): values,
gradients, gradcheck, awkward sizes, extreme inputs, determinism, and its use in training."""
import numpy as np
import pytest
import torch

from clgs.fit import losses as L
from clgs.ops.ssim import ImageLoss, SSIMError, SSIMTarget, l1_dssim


@pytest.fixture(scope="module")
def op(cl_device):
    return ImageLoss()


def _pair(shape, dtype, seed=0, noise=0.3):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=g, dtype=dtype)
    b = (a + noise * torch.rand(shape, generator=g, dtype=dtype) - noise / 2).clamp(0, 1)
    return a, b


def _reference(a, b, w_l1=1.0, w_dssim=0.25):
    """Values and gradient of w_l1 L1 + w_dssim D-SSIM with the torch functions (cached maps)."""
    a = a.detach().clone().requires_grad_(True)
    l1 = L.l1(a, b)
    ds = L.dssim(a, b, b_maps=L.target_maps(b))
    (w_l1 * l1 + w_dssim * ds).backward()
    return float(l1.detach()), float(ds.detach()), a.grad


def _cl(op, a, b, w_l1=1.0, w_dssim=0.25):
    a = a.detach().clone().requires_grad_(True)
    l1, ds = l1_dssim(a, op.target(b), op)
    (w_l1 * l1 + w_dssim * ds).backward()
    return float(l1.detach()), float(ds.detach()), a.grad


SHAPES = [(40, 33), (2, 24, 16), (3, 9, 17), (1, 1), (5, 7), (1, 12), (12, 1), (4, 3, 10)]


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_and_gradient_match_the_torch_reference(op, shape, dtype):
    """Batches, images smaller than the window, widths that are not multiples of 8."""
    a, b = _pair(shape, dtype)
    r1, rd, rg = _reference(a, b)
    c1, cd, cg = _cl(op, a, b)
    rel, gtol = (2e-6, 2e-5) if dtype == torch.float32 else (1e-13, 1e-11)
    assert c1 == pytest.approx(r1, rel=rel, abs=1e-12)
    assert cd == pytest.approx(rd, rel=10 * rel, abs=1e-12)
    assert cg.shape == a.shape and cg.dtype == dtype
    scale = float(rg.abs().max())
    assert float((cg - rg).abs().max()) <= gtol * scale, float((cg - rg).abs().max()) / scale


def test_full_size_projection_float32(op):
    """A training-sized 256 x 256 view: ~1e-5 agreement with the torch float32 reference."""
    a, b = _pair((256, 256), torch.float32, seed=3, noise=0.5)
    r1, rd, rg = _reference(a, b, 1.0, 0.25)
    c1, cd, cg = _cl(op, a, b, 1.0, 0.25)
    assert c1 == pytest.approx(r1, rel=1e-5) and cd == pytest.approx(rd, rel=1e-5)
    torch.testing.assert_close(cg, rg, rtol=1e-4, atol=1e-5 * float(rg.abs().max()))


@pytest.mark.parametrize("w", [(1.0, 0.0), (0.0, 1.0), (0.7, -2.5)])
def test_each_term_gets_its_own_gradient(op, w):
    """The backward uses the two outputs' incoming gradients separately (float64, tight)."""
    a, b = _pair((2, 13, 19), torch.float64, seed=4)
    _, _, rg = _reference(a, b, *w)
    _, _, cg = _cl(op, a, b, *w)
    torch.testing.assert_close(cg, rg, rtol=1e-10, atol=1e-14)


def test_gradcheck_float64(op):
    a, b = _pair((2, 6, 9), torch.float64, seed=5)
    target = op.target(b)
    a = a.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: l1_dssim(t, target, op), (a,), eps=1e-7, atol=1e-8)


def test_direct_2d_window_formula(op):
    """Against the textbook SSIM (the 11 x 11 window as one 2D convolution), not just our torch."""
    import torch.nn.functional as F

    a, b = _pair((23, 30), torch.float64, seed=6)
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-x * x / (2 * 1.5 ** 2))
    g = g / g.sum()
    f = lambda t: F.conv2d(t[None, None], (g[:, None] * g[None, :])[None, None], padding=5)[0, 0]  # noqa: E731
    ma, mb = f(a), f(b)
    va, vb, cov = f(a * a) - ma ** 2, f(b * b) - mb ** 2, f(a * b) - ma * mb
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ref = (((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2))).mean()
    _, ds = l1_dssim(a, op.target(b), op)
    assert float(ds) == pytest.approx(1 - float(ref), rel=1e-12)


@pytest.mark.parametrize("case", ["zeros", "constant", "equal", "huge", "huge_constant"])
def test_degenerate_and_extreme_inputs_are_finite(op, case):
    g = torch.Generator().manual_seed(7)
    shape = (2, 20, 21)
    a = torch.rand(shape, generator=g)
    b = torch.rand(shape, generator=g)
    if case == "zeros":
        a, b = torch.zeros(shape), torch.zeros(shape)
    elif case == "constant":
        a, b = torch.full(shape, 0.5), torch.full(shape, 0.25)
    elif case == "equal":
        b = a.clone()
    elif case == "huge":
        a, b = a * 1e4, b * 1e4
    else:
        a, b = torch.full(shape, 1e4), torch.full(shape, 1e4)
    c1, cd, cg = _cl(op, a, b)
    assert np.isfinite([c1, cd]).all() and torch.isfinite(cg).all()
    r1, rd, rg = _reference(a, b)
    assert c1 == pytest.approx(r1, rel=1e-5, abs=1e-6)
    if case in ("zeros", "equal"):  # SSIM(a, a) = 1 and the L1's subgradient at 0 is 0
        assert cd == pytest.approx(0.0, abs=1e-6) and float(cg.abs().max()) < 1e-4
    if case == "huge_constant":  # float32 cancellation (1e8 - 1e8): values agree, gradients are noise
        assert cd == pytest.approx(rd, abs=1e-4)
    else:
        assert cd == pytest.approx(rd, rel=1e-4, abs=1e-6)
        torch.testing.assert_close(cg, rg, rtol=1e-3, atol=max(1e-4 * float(rg.abs().max()), 1e-7))


def test_nan_render_propagates_to_the_terms(op):
    """Documented behaviour: NaN in the render gives NaN terms (the trainer then stops, below)."""
    a, b = _pair((9, 10), torch.float32)
    a[4, 6] = float("nan")
    l1, ds = l1_dssim(a, op.target(b), op)
    assert np.isnan(float(l1)) and np.isnan(float(ds))


def test_same_bits_twice_and_after_other_calls(op):
    a, b = _pair((2, 37, 45), torch.float32, seed=8)
    first = _cl(op, a, b)
    again = _cl(op, a, b)
    assert first[:2] == again[:2] and torch.equal(first[2], again[2])
    # a forward of something else between this forward and its backward: recomputed, same bits
    t = op.target(b)
    x = a.clone().requires_grad_(True)
    l1, ds = l1_dssim(x, t, op)
    other, ob = _pair((5, 7), torch.float32, seed=9)
    l1_dssim(other, op.target(ob), op)
    (l1 + 0.25 * ds).backward()
    assert torch.equal(x.grad, first[2])


def test_no_grad_forward_and_cached_maps(op):
    a, b = _pair((16, 20), torch.float32)
    with torch.no_grad():
        l1, ds = l1_dssim(a, op.target(b), op)
    assert not l1.requires_grad
    t2 = SSIMTarget(b, L.target_maps(b))  # maps given (the trainer's cache) or computed: same
    assert float(l1_dssim(a, t2, op)[1]) == float(ds)


def test_clear_errors(op):
    a, b = _pair((8, 9), torch.float32)
    t = op.target(b)
    with pytest.raises(SSIMError, match="does not match"):
        l1_dssim(a[:, :8], t, op)
    with pytest.raises(SSIMError, match="float32 or float64"):
        l1_dssim(a.half(), t, op)
    with pytest.raises(SSIMError, match="SSIMTarget"):
        l1_dssim(a, b, op)
    with pytest.raises(SSIMError, match="dtype"):
        op.forward(a.double().numpy()[None], t)
    with pytest.raises(SSIMError, match="float32 or float64"):
        SSIMTarget(torch.ones(4, 4, dtype=torch.int32))
    with pytest.raises(SSIMError, match=r"\(H, W\)"):
        SSIMTarget(torch.ones(4))


class _Ctx:
    """What ImageTerms reads from a training context."""

    def __init__(self, backend, view, render, target):
        self.trainer = type("T", (), {"backend": type("B", (), {"name": backend})()})()
        self.view, self.render, self.target = view, render, target


@pytest.mark.parametrize("backend", ["cl", "torch"])
def test_image_terms_share_one_computation_on_the_cl_backend(backend):
    a, b = _pair((24, 21), torch.float32, seed=10)
    terms = L.ImageTerms()
    r1, rd, rg = _reference(a, b, 1.0, 0.25)
    for _ in range(2):  # the second round uses the per-view caches
        x = a.clone().requires_grad_(True)
        ctx = _Ctx(backend, 3, x, b)
        v1, vd = terms.l1(ctx), terms.dssim(ctx)
        if backend == "cl":
            assert v1.grad_fn is vd.grad_fn  # one fused node for both
        (v1 + 0.25 * vd).backward()
        assert float(v1.detach()) == pytest.approx(r1, rel=1e-5) and float(vd.detach()) == pytest.approx(rd, rel=1e-5)
        torch.testing.assert_close(x.grad, rg, rtol=1e-4, atol=1e-6)
    assert (len(terms._targets), len(terms._maps)) == ((1, 0) if backend == "cl" else (0, 1))
    del ctx, v1, vd
    import gc

    gc.collect()
    assert len(terms._results) == 0  # results go with their context


def test_image_terms_without_dssim_run_no_ssim_pass():
    """A D-SSIM weight of 0 costs nothing: the L1 term alone, no SSIM target or fused pass."""
    a, b = _pair((24, 21), torch.float32, seed=11)
    terms = L.ImageTerms(dssim=False)
    x = a.clone().requires_grad_(True)
    v1 = terms.l1(_Ctx("cl", 2, x, b))
    v1.backward()
    assert float(v1.detach()) == pytest.approx(float((a - b).abs().mean()), rel=1e-6)
    torch.testing.assert_close(x.grad, torch.sign(a - b) / a.numel())
    assert len(terms._targets) == 0 and len(terms._results) == 0


def test_r2gs_with_dssim_off_builds_l1_only_terms():
    from clgs.fit.assembly import projection_losses
    from clgs.methods.r2gs import R2GSConfig

    on, off = (projection_losses(R2GSConfig(lambda_dssim=w)) for w in (0.25, 0.0))
    assert on[0].fn.__self__.fused and not off[0].fn.__self__.fused


def test_trainer_stops_on_a_nan_render():
    """A non-finite render makes the loss NaN and the trainer raises a clear FloatingPointError."""
    from clgs.geometry import Geometry
    from clgs.io.scan import Scan
    from clgs.methods.r2gs import R2GSConfig, build_trainer

    geo = Geometry.default(n_views=4, n_voxel=8, n_detector=12, volume_mm=64.0)
    proj = np.random.default_rng(0).uniform(0, 1, (4, 12, 12)).astype(np.float32)
    cfg = R2GSConfig(iterations=2, n_gaussians=20, init="random", value_scale=1.0, log_every=0,
                     checkpoint_every=0, lambda_tv=0.0)
    t = build_trainer(Scan(geo, proj), cfg)
    assert t.step()["dssim"] >= 0  # finite on the cl path
    project = t.backend.project
    t.backend.project = lambda *a, **k: project(*a, **k) * float("nan")
    with pytest.raises(FloatingPointError, match="loss became nan"):
        t.step()


def test_gpu_configuration_gives_the_same_bits():
    """The image loss as on a GPU (device buffers filled and read by copies, one row per
    work-item, the driver's work-group size), run here: the same values and gradient bits."""
    gpu = ImageLoss()
    gpu.cpu, gpu.rb, gpu.local = False, gpu.RB_GPU, None
    gpu.io.host_memory = False
    a, b = _pair((2, 37, 29), torch.float32, seed=21)
    results = [_cl(op, a, b) for op in (ImageLoss(), gpu)]
    assert results[0][1] > 0
    assert results[0][:2] == results[1][:2]
    assert torch.equal(results[0][2], results[1][2])
