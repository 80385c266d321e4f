"""Gaussian projector: forward against plain torch/NumPy references, gradients by finite
differences (float64 builds), precision agreement, determinism and extreme inputs. The key
tests run at both vector widths (8 and 16 lanes, forced), whatever the machine's own width."""
import math

import numpy as np
import pytest
import torch

from clgs.geometry import Geometry
from clgs.ops.projector import WIDE, WIDTH_ENV, GaussianProjector, ProjectorError, project, project_packed, tile_width
from clgs.reference.gaussians import covariance, precision
from clgs.reference.projection import exact_quadrature, project_dense, ray_min_q

BEAMS = ("cone", "parallel")
MODES = ("affine", "exact")
WIDTHS = (8, 16)
_projectors: dict = {}


def wproj(width):
    """A projector forced to one vector width on every kernel, built on the device the test runs
    on (one per device and width, shared): a projector keeps its device's programs, so a cache
    keyed by width alone would test the first device twice."""
    from clgs import runtime

    key = (runtime.device().int_ptr, width)
    if key not in _projectors:
        _projectors[key] = GaussianProjector(width)
    assert _projectors[key].ctx.devices[0] == runtime.device()
    return _projectors[key]


def geom(beam, n_det=40, n_views=4, off=(3.0, -5.0)):
    g = Geometry.default(n_views=n_views, mode=beam, n_detector=n_det, n_voxel=32)
    return Geometry.from_dict({**g.to_dict(), "offDetector": list(off)})


def scene(n, dtype=torch.float64, lo=0.02, hi=0.08, spread=1.2, seed=0):
    gen = torch.Generator().manual_seed(seed)
    m = (torch.rand(n, 3, generator=gen, dtype=dtype) - 0.5) * spread
    s = lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=dtype)
    q = torch.randn(n, 4, generator=gen, dtype=dtype)
    d = 0.2 + torch.rand(n, generator=gen, dtype=dtype)
    return m, s, q, d


def mats_for(mode, s, q):
    return covariance(s, q) if mode == "affine" else precision(s, q)


# ----------------------------------------------------------------------------- forward
@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("beam", BEAMS)
@pytest.mark.parametrize("mode", MODES)
def test_forward_matches_dense_reference(beam, mode, width):
    g = geom(beam)
    m, s, q, d = scene(40)
    mats = mats_for(mode, s, q)
    ref, near = project_dense(m, mats, d, g, [0, 1, 3], mode)
    assert float(ref.max()) > 1.0  # the scene is seen
    out32 = project_packed(m.float(), mats.float(), d.float(), g, [0, 1, 3], mode, wproj(width))
    out64 = project_packed(m, mats, d, g, [0, 1, 3], mode, wproj(width))
    assert out32.dtype == torch.float32 and out64.dtype == torch.float64
    keep = ~near
    # 1e-5 relative, with an absolute floor of 2e-6 of the peak for the 3-sigma tails (float32
    # pixel coordinates of a centre ~100 px off-axis carry ~1e-5 px rounding, which is 1e-5 in
    # exp(-q/2) where q is near 9)
    peak = float(ref.abs().max())
    err32 = ((out32.double() - ref).abs() / (ref.abs() + 0.2 * peak))[keep].max()
    assert err32 < 1e-5, f"float32 relative error {float(err32):.2e}"
    assert float((out64 - ref)[keep].abs().max()) < 1e-10 * float(ref.abs().max())
    assert int(near.sum()) < 0.01 * near.numel()


@pytest.mark.parametrize("beam", BEAMS)
def test_exact_matches_quadrature(beam):
    """Closed form against trapezoid integration along every ray, Gaussian by Gaussian, with
    the 3-sigma cut applied from an independent float64 distance (pixels within 0.3 of the cut
    skipped)."""
    g = geom(beam, n_det=24, n_views=1)
    m, s, q, d = scene(3, lo=0.1, hi=0.25, spread=0.8, seed=3)
    if beam == "cone":  # one Gaussian straddling the source: rays only count for t > 0
        src = torch.as_tensor(g.view_vectors()[0, :3])
        m[0] = src + torch.tensor([-0.05, 0.02, 0.0], dtype=torch.float64)
        s[0] = torch.tensor([0.4, 0.3, 0.35], dtype=torch.float64)
    P = precision(s, q)
    out = project_packed(m, P, d, g, [0], "exact")[0].numpy()
    quad = exact_quadrature(m.numpy(), P, d.numpy(), g, 0)
    qs = ray_min_q(m.numpy(), P, g, 0)
    clear = (np.abs(qs - 9.0) > 0.3).all(0)
    expect = (quad * (qs <= 9.0)).sum(0)
    assert (expect[clear] > 0).sum() > 50
    np.testing.assert_allclose(out[clear], expect[clear], rtol=1e-6, atol=1e-9 * expect.max())


def test_affine_vs_exact_error_is_small_for_small_gaussians_and_bounded_for_large():
    """The affine (R2-Gaussian) splat approximates the exact integral: measured max error over
    the peak is about 1.5e-4 for sigma = 0.25% of the volume, about 1% for sigma = 15% (where
    perspective changes across the Gaussian and the footprints' 3-sigma edges differ)."""
    g = geom("cone", n_det=64, n_views=4, off=(0, 0))
    errs = {}
    for sc in (0.005, 0.3):
        m, s, q, d = scene(20, lo=0.5 * sc, hi=1.5 * sc, seed=7)
        a = project(m, s, q, d, g, None, "affine")
        e = project(m, s, q, d, g, None, "exact")
        errs[sc] = float((a - e).abs().max() / e.abs().max())
        total = float((a.sum() - e.sum()).abs() / e.sum())
        if sc < 0.01:
            assert errs[sc] < 1e-3 and total < 5e-4, (errs[sc], total)
        else:
            assert 1e-4 < errs[sc] < 0.05 and total < 0.02, (errs[sc], total)
    # parallel beam: the affine splat is exact
    gp = geom("parallel", n_det=32, n_views=2)
    m, s, q, d = scene(20, lo=0.1, hi=0.3, seed=8)
    a = project(m, s, q, d, gp, None, "affine")
    e = project(m, s, q, d, gp, None, "exact")
    assert float((a - e).abs().max()) < 1e-10 * float(e.abs().max())


# ----------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("beam", BEAMS)
@pytest.mark.parametrize("mode", MODES)
def test_gradcheck(beam, mode, width):
    g = geom(beam, n_det=12, n_views=3)
    m, s, q, d = scene(3, lo=0.12, hi=0.25, spread=0.7, seed=11)
    args = [t.clone().requires_grad_() for t in (m, s, q, d)]
    f = lambda *a: project(*a, g, [0, 2], mode, wproj(width))  # noqa: E731
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("width", WIDTHS)
def test_gradcheck_exact_straddling_source(width):
    g = geom("cone", n_det=12, n_views=1, off=(0, 0))
    src = torch.as_tensor(g.view_vectors()[0, :3])
    m = src + torch.tensor([[0.1, 0.05, 0.0], [-0.3, 0.1, 0.1], [0.4, -0.2, 0.05]], dtype=torch.float64)
    s = torch.tensor([[0.3, 0.2, 0.25], [0.2, 0.2, 0.2], [0.4, 0.3, 0.3]], dtype=torch.float64)
    q = torch.randn(3, 4, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    d = torch.tensor([0.5, 1.0, 0.7], dtype=torch.float64)
    args = [t.clone().requires_grad_() for t in (m, s, q, d)]
    f = lambda *a: project(*a, g, [0], "exact", wproj(width))  # noqa: E731
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4)
    out = f(*args).detach()
    ref, _ = project_dense(m, precision(s, q), d, g, [0], "exact")
    assert float(ref.max()) > 1.0
    assert float((out - ref).abs().max()) < 1e-10 * float(ref.max())


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("mode", MODES)
def test_partial_and_cached_gradients_match_full(mode, width):
    """The NO_GRAD_* builds give the same numbers for what they do compute, and a backward that
    reuses the forward's set-up (token) gives the same as one that recomputes it."""
    g = geom("cone", n_det=16, n_views=2)
    m, s, q, d = scene(6, seed=5)
    mats = mats_for(mode, s, q)
    proj = GaussianProjector(width)
    gout = np.random.default_rng(0).random((2, 16, 16))
    args = (m.numpy(), mats.numpy(), d.numpy(), g, [0, 1], mode, gout)
    full = proj.backward(*args)
    proj.forward(*args[:6])
    cached = proj.backward(*args, token=proj.last_token)
    for k in range(3):
        np.testing.assert_allclose(cached[k], full[k], rtol=1e-12, atol=1e-14 * np.abs(full[k]).max())
    for needs in ((True, False, True), (False, True, False)):
        part = proj.backward(*args, needs)
        for k in range(3):
            if needs[k]:
                np.testing.assert_array_equal(part[k], full[k])
            else:
                assert part[k] is None


@pytest.mark.parametrize("beam", BEAMS)
@pytest.mark.parametrize("mode", MODES)
def test_float32_agrees_with_float64(beam, mode):
    g = geom(beam, n_det=32, n_views=2)
    m, s, q, d = scene(30, seed=9)
    a64 = [t.clone().requires_grad_() for t in (m, s, q, d)]
    a32 = [t.float().clone().requires_grad_() for t in (m, s, q, d)]
    w = torch.rand(2, 32, 32, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    o64 = project(*a64, g, [0, 1], mode)
    o32 = project(*a32, g, [0, 1], mode)
    assert float((o32.detach().double() - o64.detach()).abs().max()) < 1e-5 * float(o64.detach().abs().max())
    (o64 * w).sum().backward()
    (o32 * w.float()).sum().backward()
    for x32, x64 in zip(a32, a64):
        scale = float(x64.grad.abs().max())
        assert float((x32.grad.double() - x64.grad).abs().max()) < 2e-3 * scale



@pytest.mark.parametrize("beam", BEAMS)
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("dtype", (np.float32, np.float64))
@pytest.mark.parametrize("width", WIDTHS)
def test_gaussian_gradients_do_not_depend_on_their_neighbours(beam, mode, dtype, width):
    """The backward works on runs of Gaussians (affine: 8 per vector, one per lane); a
    Gaussian's gradient depends on dL/dI and itself only, so it must come out bit for bit the
    same whatever run or lane it lands in, with culled and partial runs around it."""
    g = geom(beam, n_det=24, n_views=3)
    m, s, q, d = scene(19, seed=12)
    if beam == "cone":  # one Gaussian at the source: culled in affine mode, straddling in exact
        m[7] = torch.as_tensor(g.view_vectors()[0, :3])
    mats = mats_for(mode, s, q)
    args = [t.numpy().astype(dtype) for t in (m, mats, d)]
    gout = np.random.default_rng(3).random((2, 24, 24)).astype(dtype)
    proj = wproj(width)
    full = proj.backward(*args, g, [0, 2], mode, gout)
    assert np.abs(full[0]).max() > 0
    for pick in ([0, 9, 18, 5], [7, 3], [18]):
        part = proj.backward(*[a[pick] for a in args], g, [0, 2], mode, gout)
        for k in range(3):
            np.testing.assert_array_equal(part[k], full[k][pick])

# ----------------------------------------------------------------------------- determinism
@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("mode", MODES)
def test_bitwise_reproducible_with_crowded_tiles(mode, width):
    g = geom("cone", n_det=64, n_views=2)
    m, s, q, d = scene(3000, dtype=torch.float32, lo=0.01, hi=0.05, spread=0.3, seed=4)
    args = [t.clone().requires_grad_() for t in (m, s, q, d)]
    proj = GaussianProjector(width)
    outs, grads = [], []
    for _ in range(2):
        for t in args:
            t.grad = None
        o = project(*args, g, [0, 1], mode, projector=proj)
        (o * o).sum().backward()
        outs.append(o.detach().clone())
        grads.append([t.grad.clone() for t in args])
    assert proj.last_pairs > 3000 * 2  # many Gaussians per tile, several tiles each
    assert torch.equal(outs[0], outs[1])
    for a, b in zip(*grads):
        assert torch.equal(a, b)
    # a fresh projector (fresh buffers) gives the same bits too
    assert torch.equal(project(*[t.detach() for t in args], g, [0, 1], mode, GaussianProjector(width)), outs[0])



@pytest.mark.parametrize("mode", MODES)
def test_tile_shape_and_chunking_do_not_change_the_image(mode):
    """Every pixel sums its Gaussians in index order with the same arithmetic lane by lane
    whatever the forward's tile and vector width (8 or 16 x 256 on CPUs, 8 x 16 or 16 x 8 on
    GPUs) and however the Gaussians are cut into chunks (each chunk's lists in their own
    region, wherever it lands), so the images agree bit for bit."""
    g = geom("cone", n_det=80, n_views=2)
    m, s, q, d = scene(400, dtype=torch.float32, lo=0.01, hi=0.06, spread=0.9, seed=6)
    mats = mats_for(mode, s, q)
    args = (m.numpy(), mats.numpy(), d.numpy(), g, [0, 1], mode)
    images = []
    for tile, chunks in (((8, 256), 32), ((8, 16), 32), ((8, 8), 1), ((16, 256), 3), ((16, 64), 7), ((16, 8), 256)):
        proj = GaussianProjector()
        proj.tile = tile
        proj.max_chunks = chunks
        images.append(proj.forward(*args))
    assert images[0].max() > 0
    for im in images[1:]:
        np.testing.assert_array_equal(im, images[0])


def test_reused_projector_matches_fresh_ones():
    """One projector (and a second sharing its compiled kernels) called with changing scenes,
    sizes, views, geometries, modes and precisions, interleaved: every call gives the bits a
    fresh projector gives. Kernel arguments are only set when they change and view parameters
    are kept per geometry, so a stale argument or parameter would show here."""
    g1, g2 = geom("cone", n_det=40, n_views=4), geom("cone", n_det=24, n_views=3, off=(0.0, 0.0))
    cases = []
    for n, seed in ((300, 1), (57, 2)):
        m, s, q, d = scene(n, dtype=torch.float32, seed=seed)
        for mode in MODES:
            mats = mats_for(mode, s, q)
            for g, views in ((g1, [0, 2]), (g2, [1]), (g1, [3])):
                for dt in (np.float32, np.float64):
                    cases.append((m.numpy().astype(dt), mats.numpy().astype(dt), d.numpy().astype(dt), g, views,
                                  mode))
    refs = []
    for c in cases:
        p = GaussianProjector(8)
        out = p.forward(*c)
        gout = np.random.default_rng(len(refs)).random(out.shape).astype(out.dtype)
        refs.append((out, gout, p.backward(*c, gout, token=p.last_token)))
    a, b = GaussianProjector(8), GaussianProjector(8)
    order = list(range(len(cases))) * 2
    np.random.default_rng(0).shuffle(order)
    for k, i in enumerate(order):
        p = (a, b)[k % 2]
        out = p.forward(*cases[i])
        np.testing.assert_array_equal(out, refs[i][0])
        grads = p.backward(*cases[i], refs[i][1], token=p.last_token)
        for x, y in zip(grads, refs[i][2]):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("mode", MODES)
def test_tile_lists_grow_when_the_guess_is_too_small(mode, width):
    """The tile lists are sized from the previous call's pairs per Gaussian (no wait for the
    count between launches); a call that needs more runs again with larger lists, once, and
    gives the same bits as a projector that never ran short."""
    g = geom("cone", n_det=64, n_views=2)
    m, s, q, d = scene(3000, dtype=torch.float32, lo=0.01, hi=0.05, spread=0.8, seed=8)
    args = (m.numpy(), mats_for(mode, s, q).numpy(), d.numpy(), g, [0, 1], mode)
    ref = GaussianProjector(width).forward(*args)
    proj = GaussianProjector(width)
    proj.tile = (width, 8)  # many (tile, Gaussian) pairs, so that a tiny guess cannot hold them
    proj._pair_ratio = 1e-4
    launches = []
    proj.on_launch = lambda name, event: launches.append(name)
    out = proj.forward(*args)
    assert proj.last_pairs > 2 * 4096  # well past the smallest lists (4096 pairs, + 25%)
    assert launches.count("preprocess") == 2 and launches.count("render") == 2
    np.testing.assert_array_equal(out, ref)
    launches.clear()
    np.testing.assert_array_equal(proj.forward(*args), ref)
    assert launches.count("preprocess") == 1  # sized right from then on


@pytest.mark.parametrize("beam", BEAMS)
@pytest.mark.parametrize("mode", MODES)
def test_vector_widths_agree(beam, mode):
    """16-lane kernels against 8-lane ones: the forward is the same arithmetic per pixel (same
    bits); the backward adds the pixels of a box in another order once a box is wider than 8
    pixels, so its gradients agree to float32 rounding of the sums (measured ~3e-7 of the
    largest entry; float64 ~1e-15), with boxes up to ~40 pixels wide here."""
    g = geom(beam, n_det=48, n_views=2)
    m, s, q, d = scene(60, lo=0.01, hi=0.25, spread=0.9, seed=13)
    mats = mats_for(mode, s, q)
    for dt, tol in ((np.float32, 4e-6), (np.float64, 1e-12)):
        args = (m.numpy().astype(dt), mats.numpy().astype(dt), d.numpy().astype(dt), g, [0, 1], mode)
        gout = np.random.default_rng(5).random((2, 48, 48)).astype(dt)
        res = {}
        for w in WIDTHS:
            p = wproj(w)
            assert p.widths(beam, mode) == (w, w)
            out = p.forward(*args)
            res[w] = (out, p.backward(*args, gout, token=p.last_token))
        assert res[8][0].max() > 1.0
        np.testing.assert_array_equal(res[16][0], res[8][0])
        for g16, g8 in zip(res[16][1], res[8][1]):
            scale = np.abs(g8).max()
            assert scale > 0
            np.testing.assert_allclose(g16, g8, rtol=0, atol=tol * scale)


def test_vector_width_choice(monkeypatch):
    """16 lanes where the device's native float vector has 16 (per kernel as WIDE says), 8
    elsewhere; $CLGS_TILE_WIDTH forces one width on every kernel."""

    class Dev:
        def __init__(self, n):
            self.native_vector_width_float = n

    monkeypatch.delenv(WIDTH_ENV, raising=False)
    assert tile_width(Dev(16)) == (16, False)
    assert tile_width(Dev(8)) == (8, False) and tile_width(Dev(4)) == (8, False)
    monkeypatch.setenv(WIDTH_ENV, "16")
    assert tile_width(Dev(8)) == (16, True)
    p = GaussianProjector()
    assert p.forced and all(p.widths(b, m) == (16, 16) for b in BEAMS for m in MODES)
    assert p.tile_for("cone", "exact")[0] == 16
    opts = p.program("cone", "exact", "float").options
    assert "-DTW=16" in opts and "-DBW=16" in opts
    monkeypatch.setenv(WIDTH_ENV, "8")
    assert all(GaussianProjector().widths(b, m) == (8, 8) for b in BEAMS for m in MODES)
    monkeypatch.setenv(WIDTH_ENV, "12")
    with pytest.raises(ProjectorError, match="CLGS_TILE_WIDTH must be 8 or 16"):
        GaussianProjector()
    with pytest.raises(ProjectorError, match="width must be 8 or 16"):
        GaussianProjector(4)
    # automatic width 16: each kernel as measured (the exact cone stays at 8 lanes)
    p = GaussianProjector(16)
    p.forced = False
    for key, (tw, bw) in WIDE.items():
        assert p.widths(*key) == (tw, bw)
        assert p.tile_for(*key)[0] == tw
        opts = p.program(*key, "float").options
        assert f"-DTW={tw}" in opts and f"-DBW={bw}" in opts
    assert WIDE[("cone", "affine")] == (16, 16)


# ----------------------------------------------------------------------------- extremes
def _finite_fwd_bwd(m, s, q, d, g, mode, views=None, projector=None):
    args = [t.clone().requires_grad_() for t in (m, s, q, d)]
    o = project(*args, g, views, mode, projector)
    assert torch.isfinite(o).all()
    o.sum().backward()
    for t in args:
        assert torch.isfinite(t.grad).all()
    return o.detach()


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("dtype", (torch.float32, torch.float64))
@pytest.mark.parametrize("width", WIDTHS)
def test_extreme_scales_thinness_and_densities(mode, dtype, width):
    g = geom("cone", n_det=48, n_views=2)
    gen = torch.Generator().manual_seed(3)
    n = 60
    m = ((torch.rand(n, 3, generator=gen) - 0.5) * 1.5).to(dtype)
    size = torch.logspace(math.log10(2e-4), math.log10(2.0), n).to(dtype)  # 1e-4 to 1 of the volume
    s = size[:, None].repeat(1, 3)
    s[0::3, 0] *= 1e-3  # pancakes
    s[1::3, 1:] *= 1e-3  # needles
    q = torch.randn(n, 4, generator=gen).to(dtype)
    d = torch.logspace(-8, 4, n).to(dtype)[torch.randperm(n, generator=gen)]
    o = _finite_fwd_bwd(m, s, q, d, g, mode, projector=wproj(width))
    assert float(o.max()) > 0


@pytest.mark.parametrize("dtype", (torch.float32, torch.float64))
@pytest.mark.parametrize("width", WIDTHS)
def test_on_and_behind_source_plane(dtype, width):
    """Cone beam: exact mode integrates Gaussians at/behind the source (t > 0 only), affine
    culls them; neither gives NaN/Inf."""
    g = geom("cone", n_det=24, n_views=1, off=(0, 0))
    src = torch.as_tensor(g.view_vectors()[0, :3], dtype=dtype)
    axis = -src / torch.linalg.vector_norm(src)
    offsets = [0.0, -0.05, -0.5, 0.02, 0.3]  # along the axis: on, behind, far behind, in front
    m = torch.stack([src + o * axis + torch.tensor([0, 0.01 * i, 0], dtype=dtype) for i, o in enumerate(offsets)])
    s = torch.tensor([[0.1, 0.1, 0.1], [0.05, 0.2, 0.1], [0.05, 0.05, 0.05], [1e-4, 1e-4, 1e-4], [0.2, 0.2, 0.2]],
                     dtype=dtype)
    q = torch.tensor([[1.0, 0, 0, 0]] * 5, dtype=dtype)
    d = torch.ones(5, dtype=dtype)
    e = _finite_fwd_bwd(m, s, q, d, g, "exact", projector=wproj(width))
    a = _finite_fwd_bwd(m, s, q, d, g, "affine", projector=wproj(width))
    ref, near = project_dense(m.double(), precision(s, q).double(), d.double(), g, [0], "exact")
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    assert float(ref.max()) > 1.0
    assert float((e.double() - ref)[~near].abs().max()) < tol * float(ref.max())
    assert float(a.abs().max()) < float(e.max())  # the near ones are culled in affine mode


@pytest.mark.parametrize("mode", MODES)
def test_grazing_ray_on_edge_on_pancake(mode):
    """A pancake whose thin axis is perpendicular to the rays (seen edge-on) and one seen face-on."""
    for beam in BEAMS:
        g = geom(beam, n_det=65, n_views=1, off=(0, 0))  # odd: the central ray hits pixel 32
        # view 0: rays along -x; pancake thin along y (edge-on) and thin along x (face-on)
        m = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.2, 0.1]], dtype=torch.float32)
        s = torch.tensor([[0.3, 3e-4, 0.3], [3e-4, 0.2, 0.2]], dtype=torch.float32)
        q = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=torch.float32)
        d = torch.tensor([1.0, 1.0], dtype=torch.float32)
        o = _finite_fwd_bwd(m, s, q, d, g, mode, [0])
        ref, near = project_dense(m.double(), (covariance if mode == "affine" else precision)(s.double(), q.double()),
                                  d.double(), g, [0], mode)
        assert float(o.max()) > 0
        # edge-on: the line integral along the pancake's plane is long (about 2 sqrt(2 pi) 0.3 / scale)
        assert float(ref.max()) > 0.5 * math.sqrt(2 * math.pi) * 0.3 / g.scale
        rel = float((o.double() - ref)[~near].abs().max() / ref.max())
        assert rel < 2e-3, rel  # a 1e-3-thin sheet in float32: bounded by the input's rounding


@pytest.mark.parametrize("n_det", (1, 2048))
@pytest.mark.parametrize("width", WIDTHS)
def test_tiny_and_huge_detectors(n_det, width):
    g = Geometry.default(n_views=2, mode="cone", n_detector=n_det, n_voxel=32)
    m, s, q, d = scene(5, dtype=torch.float32, lo=0.05, hi=0.2, spread=0.3)
    for mode in MODES:
        o = _finite_fwd_bwd(m, s, q, d, g, mode, [1], wproj(width))
        assert o.shape == (1, n_det, n_det)
        assert float(o.max()) > 0
        if n_det == 2048:
            # the central 64 x 64 pixels are those of a 64-pixel detector with the same pitch
            crop = Geometry.from_dict({**g.to_dict(), "nDetector": [64, 64]})
            ref, near = project_dense(m.double(), mats_for(mode, s, q).double(), d.double(), crop, [1], mode)
            part = o[:, 992:1056, 992:1056].detach().double()
            assert float(ref.max()) > 0.1 * float(o.max())
            assert float((part - ref)[~near].abs().max()) < 1e-5 * float(ref.max())


def test_no_gaussians_and_zero_densities():
    g = geom("cone", n_det=16, n_views=2)
    for mode in MODES:
        e = torch.zeros(0, 3, requires_grad=True)
        o = project(e, torch.ones(0, 3), torch.ones(0, 4), torch.zeros(0), g, None, mode)
        assert o.shape == (2, 16, 16) and float(o.detach().abs().max()) == 0.0
        o.sum().backward()
        assert e.grad.shape == (0, 3)
        m, s, q, d = scene(10, dtype=torch.float32)
        o = _finite_fwd_bwd(m, s, q, torch.zeros(10), g, mode)
        assert float(o.abs().max()) == 0.0


def test_clear_errors():
    g = geom("cone", n_det=8, n_views=2)
    m, s, q, d = scene(4, dtype=torch.float32)
    with pytest.raises(ProjectorError, match="mode"):
        project(m, s, q, d, g, None, "bogus")
    with pytest.raises(ProjectorError, match="scales"):
        project(m, s[:3], q, d, g)
    with pytest.raises(ProjectorError, match="NaN"):
        project(m * float("nan"), s, q, d, g)
    with pytest.raises(ProjectorError, match="positive"):
        project(m, -s, q, d, g)
    with pytest.raises(ProjectorError, match="dtype"):
        project(m, s.double(), q, d, g)
    with pytest.raises(ProjectorError, match="view"):
        project(m, s, q, d, g, [5])
    with pytest.raises(ProjectorError, match="zero"):
        project(m, s, torch.zeros_like(q), d, g)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("mode", MODES)
def test_portable_exp_gives_the_same_bits(mode, width):
    """2^t in the splat loops: the AVX-512 split (vreduceps, vcvtps2dq) and the portable one (add
    and take away 1.5 2^23) give the same bits, here over images and gradients of crowded tiles,
    where millions of exponents are taken (ties included: t = k + 1/2 rounds to even both ways)."""
    g = geom("cone", n_det=64, n_views=2)
    m, s, q, d = scene(1500, dtype=torch.float32, lo=0.01, hi=0.1, spread=1.0, seed=21)
    args = (m.numpy(), mats_for(mode, s, q).numpy(), d.numpy(), g, [0, 1], mode)
    gout = np.random.default_rng(7).random((2, *g.nDetector), dtype=np.float32)
    results = []
    for defines in ({}, {"PORTABLE_EXP": 1}):
        proj = GaussianProjector(width)
        proj.extra_defines = defines
        img = proj.forward(*args)
        results.append((img, proj.backward(*args, gout, token=proj.last_token)))
    (a, ga), (b, gb) = results
    assert a.max() > 0 and np.array_equal(a, b)
    for x, y in zip(ga, gb):
        assert np.array_equal(x, y)


def _as_on_a_gpu(proj):
    """The projector configured as on a GPU (device buffers filled by copies and read back by
    copies, GPU work-group sizes, one Gaussian per backward work-item, GPU tiles), on this device."""
    proj.cpu = proj.io.host_memory = False
    proj.extra_defines = {"PORTABLE_EXP": 1}  # no x86 builtins (cl/project_setup.h) on a GPU
    proj.LOCAL_G, proj.LOCAL_TILE, proj.PER = proj.LOCAL_G_GPU, proj.LOCAL_TILE_GPU, proj.PER_GPU
    proj.max_chunks = 256
    return proj


@pytest.mark.parametrize("beam", ["cone", "parallel"])
@pytest.mark.parametrize("mode", MODES)
def test_gpu_configuration_gives_the_same_bits(beam, mode):
    """The code paths a GPU takes (copies instead of wrapped host memory, other work-group and
    tile sizes, 2^t without AVX-512 builtins) run here on the CPU device and give the CPU
    configuration's images and gradients bit for bit: the sums are in Gaussian order whatever the
    launch shape, and both ways of splitting t round to nearest even."""
    g = geom(beam, n_det=36, n_views=3)
    m, s, q, d = scene(300, dtype=torch.float32, lo=0.01, hi=0.07, spread=1.0, seed=8)
    args = (m.numpy(), mats_for(mode, s, q).numpy(), d.numpy(), g, [0, 2], mode)
    gout = np.random.default_rng(3).random((2, *g.nDetector), dtype=np.float32)
    results = []
    for proj in (GaussianProjector(), _as_on_a_gpu(GaussianProjector())):
        img = proj.forward(*args)
        grads = proj.backward(*args, gout, token=proj.last_token)
        results.append((img, grads))
    (a, ga), (b, gb) = results
    assert a.max() > 0 and np.array_equal(a, b)
    for x, y in zip(ga, gb):
        assert np.array_equal(x, y)
