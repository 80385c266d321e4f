"""GaussianSet activations, initialisation from a volume, densification / pruning (no kernels)."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from clgs.fit.gaussians import (
    Densifier,
    GaussianSet,
    Schedule,
    init_from_volume,
    init_random,
    inverse_softplus,
    r2gs_schedules,
)
from clgs.geometry import Geometry, Grid

BOX = (1.0, 1.0, 1.0)


def _grid(n=16):
    sp = 2.0 / n
    o = -1 + sp / 2
    return Grid((n, n, n), (o, o, o), (sp, sp, sp))


def test_inverse_softplus_round_trip():
    x = torch.tensor([1e-6, 1e-3, 0.15, 1.0, 30.0, 100.0], dtype=torch.float64)
    assert torch.allclose(F.softplus(inverse_softplus(x)), x, rtol=1e-9, atol=0)


def test_bounded_scales_stay_in_bounds_and_invert():
    s = np.full((4, 3), 0.02, np.float32)
    s[1] = [0.001, 0.3, 0.999]
    g = GaussianSet(np.zeros((4, 3)), s, np.tile([1.0, 0, 0, 0], (4, 1)), np.full(4, 0.5), box=BOX)
    lo, hi = g.scale_range
    assert (lo, hi) == pytest.approx((0.001, 1.0))
    _, scales, _, dens = g.tensors()
    assert torch.allclose(scales[2:], torch.tensor(s[2:]), rtol=1e-4)
    assert torch.allclose(dens, torch.full((4,), 0.5), rtol=1e-6)
    with torch.no_grad():
        g.params["scales"].fill_(1e4)
    assert float(g.tensors()[1].detach().max()) <= hi
    with torch.no_grad():
        g.params["scales"].fill_(-1e4)
    assert float(g.tensors()[1].detach().min()) >= lo
    e = GaussianSet(np.zeros((1, 3)), [[0.05, 0.2, 3.0]], [[1.0, 0, 0, 0]], [0.1], box=BOX, scale_bounds=None)
    assert torch.allclose(e.tensors()[1], torch.tensor([[0.05, 0.2, 3.0]]), rtol=1e-6)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="means"):
        GaussianSet(np.zeros((3, 2)), np.ones((3, 3)), np.ones((3, 4)), np.ones(3), box=BOX)
    with pytest.raises(ValueError, match="NaN"):
        GaussianSet(np.full((1, 3), np.nan), np.ones((1, 3)) * 0.1, np.ones((1, 4)), np.ones(1), box=BOX)


def test_init_from_volume_counts_positions_densities_scales():
    grid = _grid(16)
    vol = np.zeros(grid.shape, np.float32)
    vol[4:10, 5:11, 6:12] = 2.0  # 216 voxels: all above threshold
    vol[0, 0, 0] = 0.09  # 4.5 % of the range: below the 5 % threshold
    vol[15, 15, 15] = 0.11  # 5.5 %: kept
    g = init_from_volume(vol, grid, box=BOX, n_gaussians=50_000)
    assert len(g) == 217
    means, scales, quats, dens = g.tensors()
    # every mean is a voxel centre of a kept voxel
    idx = np.rint((means.detach().numpy() - np.asarray(grid.origin)) / np.asarray(grid.spacing)).astype(int)
    assert np.allclose(means.detach().numpy(), np.asarray(grid.origin) + idx * np.asarray(grid.spacing), atol=1e-6)
    vals = vol[idx[:, 2], idx[:, 1], idx[:, 0]]
    assert np.all(vals > 0.1)
    assert np.allclose(dens.detach().numpy(), 0.15 * vals, rtol=1e-5)
    # isotropic scale: in the cube the 3 nearest neighbours are one voxel away
    in_cube = vals == 2.0
    assert np.allclose(scales.detach().numpy()[in_cube], grid.spacing[0], rtol=1e-5)
    assert torch.all(quats == torch.tensor([1.0, 0, 0, 0]))


def test_init_from_volume_samples_without_replacement_and_is_seeded():
    grid = _grid(16)
    vol = np.zeros(grid.shape, np.float32)
    vol[2:14, 2:14, 2:14] = 1.0  # 1728 candidates
    a = init_from_volume(vol, grid, box=BOX, n_gaussians=500, seed=3)
    b = init_from_volume(vol, grid, box=BOX, n_gaussians=500, seed=3)
    c = init_from_volume(vol, grid, box=BOX, n_gaussians=500, seed=4)
    ma = a.params["means"].detach().numpy()
    assert len(a) == 500
    assert np.unique(ma, axis=0).shape[0] == 500
    assert np.array_equal(ma, b.params["means"].detach().numpy())
    assert not np.array_equal(ma, c.params["means"].detach().numpy())
    # sparser sampling -> larger nearest-neighbour scale than the voxel spacing
    assert float(a.tensors()[1].detach().mean()) > 1.2 * grid.spacing[0]


def test_init_errors():
    grid = _grid(8)
    with pytest.raises(ValueError, match="constant"):
        init_from_volume(np.zeros(grid.shape), grid, box=BOX)
    with pytest.raises(ValueError, match="shape"):
        init_from_volume(np.zeros((4, 4, 4)), grid, box=BOX)
    r = init_random(100, box=(0.5, 0.4, 0.3), seed=0)
    m = r.params["means"].detach().numpy()
    assert len(r) == 100 and np.all(np.abs(m) <= [0.5, 0.4, 0.3])


def test_schedules():
    s = Schedule(2e-4, 2e-5, 1000)
    assert s(0) == pytest.approx(2e-4) and s(1000) == pytest.approx(2e-5) and s(5000) == pytest.approx(2e-5)
    assert s(500) == pytest.approx(np.sqrt(2e-4 * 2e-5))
    alpha = Schedule(0.1, 0.001, 450, start=50, frozen_before_start=True)
    assert alpha(0) == 0 and alpha(49) == 0 and alpha(50) == pytest.approx(0.1) and alpha(500) == pytest.approx(1e-3)
    d = r2gs_schedules(30_000)
    assert d["means"](0) == pytest.approx(2e-4) and d["quats"](30_000) == pytest.approx(1e-4)
    doubled = r2gs_schedules(30_000, 2.0)  # lr_factor: every rate and its decay's end, times the factor
    for name in d:
        for it in (0, 10_000, 30_000):
            assert doubled[name](it) == pytest.approx(2 * d[name](it))


# ---------------------------------------------------------------------- densification
def _geo(mode="parallel"):
    return Geometry.default(n_views=4, n_voxel=16, n_detector=32, volume_mm=64.0, mode=mode)


def _set_with_adam(n, scales, dens=0.5, means=None):
    means = np.zeros((n, 3)) if means is None else means
    g = GaussianSet(means, scales, np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, dens), box=BOX, name="free")
    opt = torch.optim.Adam([{"params": [p]} for p in g.params.values()], eps=1e-15)
    for p in g.params.values():
        p.grad = torch.ones_like(p)
    opt.step()
    return g, opt


def test_densify_clone_split_prune_and_adam_state():
    n = 6
    scales = np.full((n, 3), 0.05)
    scales[1] = [0.4, 0.05, 0.05]  # large: split
    means = np.zeros((n, 3))
    means[4] = [1.5, 0, 0]  # outside the box: pruned
    g, opt = _set_with_adam(n, scales, means=means)
    with torch.no_grad():
        g.params["densities"][5] = inverse_softplus(torch.tensor(1e-7))  # faint: pruned
    dens0 = g.tensors()[3].detach().clone()
    scales0 = g.tensors()[1].detach().clone()
    d = Densifier(_geo(), max_gaussians=100)
    grad = torch.tensor([1e-4, 1e-4, 0, 0, 0, 0])  # 0 is cloned, 1 split
    d.stats["free"] = (grad.clone(), torch.ones(n))
    exp_avg_2 = opt.state[g.params["means"]]["exp_avg"][2].clone()
    res = d.densify_and_prune(g, opt, torch.Generator().manual_seed(0))
    assert res == {"cloned": 1, "split": 1, "pruned": 2, "count": 6}
    m, s, q, dd = g.tensors()
    # kept originals 0, 2, 3 then the clone of 0 then the 2 children of 1
    assert torch.allclose(dd[0], dens0[0] * 0.5, rtol=1e-5) and torch.allclose(dd[3], dens0[0] * 0.5, rtol=1e-5)
    assert torch.allclose(dd[1:3], dens0[2:4])
    assert torch.allclose(s[4:6], scales0[1].expand(2, 3) / 1.6, rtol=1e-4)
    assert torch.allclose(dd[4:6], dens0[1].expand(2) * 0.5, rtol=1e-5)  # R2-Gaussian: each child halves
    assert not torch.equal(m[4], m[5])
    # Adam state follows the rows; new rows start at zero; optimizer holds the new tensors
    st = opt.state[g.params["means"]]
    assert st["exp_avg"].shape == (6, 3)
    assert torch.equal(st["exp_avg"][1], exp_avg_2)
    assert torch.all(st["exp_avg"][3:] == 0) and torch.all(st["exp_avg_sq"][3:] == 0)
    assert {id(p) for grp in opt.param_groups for p in grp["params"]} == {id(p) for p in g.params.values()}


def test_densify_respects_the_cap_largest_gradients_first():
    n = 20
    g, opt = _set_with_adam(n, np.full((n, 3), 0.05))
    dens0 = g.tensors()[3].detach().clone()
    d = Densifier(_geo(), max_gaussians=25)
    grad = torch.linspace(1e-4, 2e-4, n)  # all above threshold; the 5 largest are the last 5
    d.stats["free"] = (grad, torch.ones(n))
    res = d.densify_and_prune(g, opt, torch.Generator().manual_seed(0))
    assert res["cloned"] == 5 and len(g) == 25
    dens = g.tensors()[3].detach()
    assert torch.allclose(dens[15:20], dens[20:25])  # the clones are of the last five
    assert torch.allclose(dens[15:20], dens0[15:20] * 0.5, rtol=1e-5)
    assert torch.allclose(dens[:15], dens0[:15], rtol=1e-6)
    d.stats["free"] = (torch.full((25,), 1.0), torch.ones(25))
    d.densify_and_prune(g, opt, torch.Generator().manual_seed(0))
    assert len(g) == 25  # at the cap: nothing added


def test_densifier_schedule():
    d = Densifier(_geo())
    assert [i for i in range(0, 16_000, 50) if d.due(i)][:3] == [500, 600, 700]
    assert d.due(15_000) and not d.due(15_100) and not d.due(400) and not d.due(550)


@pytest.mark.parametrize("mode", ["parallel", "cone"])
def test_view_space_gradient_matches_the_detector_coordinate_gradient(mode):
    """For a loss of the Gaussian's normalised detector position, the reconstructed view-space
    gradient equals |dL/dNDC| (exactly at the centre of the view, to a few % off-centre)."""
    geo = _geo(mode)
    d = Densifier(geo)
    vec = torch.tensor(geo.view_vectors(scene=True)[1])
    nv, nu = geo.nDetector
    half_u, half_v = 0.5 * nu * vec[6:9].norm(), 0.5 * nv * vec[9:12].norm()
    eu, ev = vec[6:9] / vec[6:9].norm(), vec[9:12] / vec[9:12].norm()
    for p in ([0.0, 0.0, 0.0], [0.05, -0.03, 0.04], [0.2, 0.1, -0.1]):
        mean = torch.tensor([p], dtype=torch.float64, requires_grad=True)
        if mode == "cone":
            src = vec[0:3]
            ray = mean[0] - src
            axis = (vec[3:6] - src)
            axis = axis / axis.norm()
            hit = src + ray * (geo.DSD * geo.scale / (ray @ axis))
        else:
            hit = mean[0]
        ndc = torch.stack([((hit - vec[3:6]) @ eu) / half_u, ((hit - vec[3:6]) @ ev) / half_v])
        w = torch.tensor([0.3, -0.7], dtype=torch.float64)
        (w @ ndc).backward()
        got = d.view_space_grad(mean.detach(), mean.grad, 1)
        tol = 1e-9 if p[0] == 0 else 0.05
        assert float(got) == pytest.approx(float(w.norm()), rel=tol)


def test_training_covariances_match_gaussian_math_values_and_gradients():
    """What training feeds the kernels (the OpenCL cov_prec) against the torch reference."""
    from clgs.ops.voxelizer import cov_prec
    from clgs.reference import gaussians as gm

    g = torch.Generator().manual_seed(0)
    s = (torch.rand(50, 3, generator=g, dtype=torch.float64) * 0.3 + 1e-3).requires_grad_(True)
    q = torch.randn(50, 4, generator=g, dtype=torch.float64).requires_grad_(True)
    for inverse, ref in ((False, gm.covariance), (True, gm.precision)):
        a, b = cov_prec(s, q, cov=not inverse, prec=inverse)[1 if inverse else 0], ref(s, q)
        assert torch.allclose(a, b, rtol=1e-12, atol=0)
        w = torch.randn(50, 6, generator=g, dtype=torch.float64)
        ga = torch.autograd.grad((a * w).sum(), (s, q))
        gb = torch.autograd.grad((b * w).sum(), (s, q))
        assert all(torch.allclose(x, y, rtol=1e-10, atol=1e-12) for x, y in zip(ga, gb))
    f32 = cov_prec(s.detach().float(), q.detach().float(), cov=False, prec=True)[1]
    assert torch.allclose(f32.double(), gm.precision(s, q).detach(), rtol=1e-5, atol=1e-6 * float(f32.abs().max()))
    ext = cov_prec(s.detach(), q.detach(), cov=False, prec=False, extent=True)[2]
    assert torch.allclose(ext, gm.axis_extent(s, q), rtol=1e-12)
