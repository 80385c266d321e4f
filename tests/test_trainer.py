"""The training loop on a tiny scene: convergence, bit-for-bit resume, Ctrl-C, densification cap,
zero-weight terms, and the r2gs method end to end (OpenCL backend unless stated)."""
import os
import signal

import numpy as np
import pytest
import torch
from gaussian_scene import six_gaussian_scan

from clgs.fit import checkpoint as ckpt
from clgs.fit.assembly import value_scale_from
from clgs.fit.trainer import LossTerm
from clgs.geometry import Geometry
from clgs.io.scan import Scan
from clgs.methods.r2gs import R2GSConfig, build_trainer, reconstruct_r2gs


@pytest.fixture(scope="module")
def scene():
    """6 anisotropic Gaussians (attenuation ~0.01-0.02 /mm) in a 64 mm cube, 8 cone-beam views."""
    return six_gaussian_scan()


SMALL = dict(n_gaussians=150, densify_start=10, densify_interval=10, densify_until=30, log_every=10,
             checkpoint_every=0, max_gaussians=600)


def _cfg(iterations, **kw):
    return R2GSConfig(**{**SMALL, "iterations": iterations, **kw})


def _trainer(scene, iterations, out=None, backend="cl", **kw):
    return build_trainer(scene, _cfg(iterations, backend=backend, init="random", value_scale=60.0, **kw), out)


def _same_state(a, b):
    for sa, sb in zip(a.sets, b.sets):
        for k in sa.params:
            assert torch.equal(sa.params[k], sb.params[k]), k
    oa, ob = a.optimizer.state_dict(), b.optimizer.state_dict()
    for i in oa["state"]:
        for k in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(oa["state"][i][k], ob["state"][i][k]), (i, k)
    assert torch.equal(a.generator.get_state(), b.generator.get_state())
    assert a.view_stack == b.view_stack and a.iteration == b.iteration
    strip = lambda rows: [{k: v for k, v in r.items() if k not in ("seconds", "wall")} for r in rows]  # noqa: E731
    assert strip(a.log.rows) == strip(b.log.rows)


def test_tiny_scene_converges(scene):
    """From a random start the projection L1 falls by more than an order of magnitude."""
    t = _trainer(scene, 300, lambda_tv=0.05, densify_until=200, densify_interval=50, densify_start=50)
    l1 = [t.step()["l1"] for _ in range(300)]
    assert np.isfinite(l1).all()
    assert np.mean(l1[-20:]) < np.mean(l1[:5]) / 10, (np.mean(l1[:5]), np.mean(l1[-20:]))
    assert t.n_gaussians > 150  # densification happened


@pytest.mark.parametrize("backend", ["cl", "torch"])
def test_resume_is_bit_for_bit(scene, tmp_path, backend):
    """N iterations straight == K + checkpoint + a fresh resume to N, with densification on the way
    (and, on the OpenCL backend, TV patches drawn from the generator and the evaluations)."""
    if backend == "cl":
        n, k, kw = 30, 17, {}
    else:  # the plain-torch iteration is slow: a smaller run
        n, k, kw = 12, 7, dict(n_gaussians=60, lambda_tv=0.0, log_every=0, densify_start=5, densify_interval=5)
    whole = _trainer(scene, n, backend=backend, **kw).fit()
    first = _trainer(scene, n, tmp_path, backend=backend, **kw)  # the lr schedules span n iterations
    first.iterations = k  # stop early, as an interrupted run would
    first.fit()
    assert (tmp_path / "checkpoint.pt").is_file()
    state = ckpt.load(tmp_path / "checkpoint.pt")
    assert state["iteration"] == k
    if kw.get("log_every", 10):  # the log file follows the run, not only its end
        from clgs.fit.training_log import TrainingLog

        assert [r["iteration"] for r in TrainingLog.read_csv(tmp_path / "log.csv").rows] == [0, 10, k]
    resumed = _trainer(scene, n, tmp_path, backend=backend, **kw)
    resumed.load_state_dict(state)
    resumed.fit()
    _same_state(whole, resumed)
    assert len(whole.sets[0]) != 60 if backend == "torch" else len(whole.sets[0]) != 150  # densified


def test_ctrl_c_from_a_hook_saves_a_checkpoint_that_resumes_exactly(scene, tmp_path):
    class Interrupt:
        def on_iteration(self, trainer):
            if trainer.iteration == 7:
                raise KeyboardInterrupt

    t = _trainer(scene, 20, tmp_path)
    t.hooks.append(Interrupt())
    t.fit()
    assert t.interrupted and t.iteration == 7
    state = ckpt.load(tmp_path / "checkpoint.pt")
    assert state["iteration"] == 7
    assert [r["iteration"] for r in ckpt.loads(state["log"])] == [0] and state["count"] == 7  # the log travels too
    assert t.log.rows[-1]["iteration"] == 7  # ... and the outputs show the figures at the interruption
    resumed = _trainer(scene, 20, tmp_path)
    resumed.load_state_dict(state)
    resumed.fit()
    _same_state(_trainer(scene, 20).fit(), resumed)


def test_sigint_stops_at_the_end_of_the_iteration(scene, tmp_path):
    class Press:
        def after_backward(self, trainer, ctx):  # mid-iteration, as a real Ctrl-C would land
            if trainer.iteration == 4:
                os.kill(os.getpid(), signal.SIGINT)

    t = _trainer(scene, 20, tmp_path)
    t.hooks.append(Press())
    before = signal.getsignal(signal.SIGINT)
    t.fit()
    assert signal.getsignal(signal.SIGINT) is before
    assert t.interrupted and t.iteration == 5  # the interrupted iteration completed
    assert ckpt.load(tmp_path / "checkpoint.pt")["iteration"] == 5


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_saves_the_iteration_it_landed_in_and_is_recorded(scene, tmp_path, sig):
    """SIGTERM (timeout, batch schedulers, container stops) saves as Ctrl-C does; the trainer
    records which signal stopped it, so commands can exit with 128 + its number."""
    class Send:
        def after_backward(self, trainer, ctx):
            if trainer.iteration == 3:
                os.kill(os.getpid(), sig)

    t = _trainer(scene, 20, tmp_path)
    t.hooks.append(Send())
    before = signal.getsignal(sig)
    t.fit()
    assert signal.getsignal(sig) is before
    assert t.interrupted and t.iteration == 4 and t.stop_signal == sig
    assert ckpt.load(tmp_path / "checkpoint.pt")["iteration"] == 4
    done = _trainer(scene, 20, tmp_path).fit()
    assert not done.interrupted and done.stop_signal is None


def test_densification_respects_the_cap(scene):
    t = _trainer(scene, 60, max_gaussians=200, densify_interval=5, densify_start=5, densify_until=60)
    counts = []
    t.hooks.append(type("Count", (), {"on_iteration": lambda self, tr: counts.append(tr.n_gaussians)})())
    t.fit()
    assert max(counts) == 200 and all(c <= 200 for c in counts)


def test_densification_statistics_see_the_projection_gradient_only(scene):
    """As R2-Gaussian's view-space gradient: the TV term moves the means but must not change
    which Gaussians get densified."""
    stats, moved = [], []
    for tv in (0.0, 5.0):
        t = _trainer(scene, 1, lambda_tv=tv, tv_size=8)
        m0 = t.sets[0].params["means"].detach().clone()
        t.fit()
        dens = next(h for h in t.hooks if hasattr(h, "stats"))
        stats.append(dens.stats["free"])
        moved.append(t.sets[0].params["means"].detach() - m0)
    assert not torch.equal(moved[0], moved[1])  # the TV term did act on the means
    (acc0, cnt0), (acc1, cnt1) = stats
    assert float(acc0.sum()) > 0 and int(cnt0.sum()) > 0
    assert torch.equal(acc0, acc1) and torch.equal(cnt0, cnt1)


def test_zero_weight_terms_are_never_computed(scene, monkeypatch):
    import clgs.fit.tv_patch

    def boom(ctx):
        raise AssertionError("a zero-weight term was evaluated")

    calls = []
    tv = clgs.fit.tv_patch.patch_tv
    monkeypatch.setattr(clgs.fit.tv_patch, "patch_tv", lambda backend, tensors, grid: calls.append(grid.shape)
                        or tv(backend, tensors, grid))
    t = _trainer(scene, 5, lambda_tv=0.0)
    t.losses.append(LossTerm("boom", 0.0, boom))
    t.evaluate = None
    t.fit()
    assert calls == []  # TV weight 0: no patch voxelised
    assert "tv" not in t.log.rows[-1] and "boom" not in t.log.rows[-1]
    t2 = _trainer(scene, 3, lambda_tv=0.05)
    t2.evaluate = None
    t2.fit()
    assert calls == [(15, 15, 15)] * 3  # a 32^3 patch, clipped to this 16^3 volume (less one: the sub-voxel shift)


def test_frozen_parameters_do_not_move(scene):
    from clgs.fit.gaussians import Schedule

    t = _trainer(scene, 5)
    s = t.sets[0]
    s.schedules["means"] = Schedule(1e-2, start=3, frozen_before_start=True)
    t._build_optimizer()
    m0 = s.params["means"].detach().clone()
    for _ in range(3):
        t.step()
    assert torch.equal(s.params["means"], m0)
    assert s.params["means"] not in t.optimizer.state or not t.optimizer.state[s.params["means"]]
    t.step()
    assert not torch.equal(s.params["means"], m0)


def test_normalisation_maps_the_fdk_percentile_to_one():
    vol = np.zeros((20, 20, 20), np.float32)
    vol[:10] = 0.02
    vol[0, 0, 0] = 5.0  # a hot voxel is ignored by the 99.9th percentile
    assert value_scale_from(vol) == pytest.approx(1 / 0.02, rel=0.01)
    with pytest.raises(ValueError, match="percentile"):
        value_scale_from(np.zeros((4, 4, 4)))


def test_reconstruct_r2gs_writes_outputs_and_resumes(scene, tmp_path):
    out = tmp_path / "run"
    res = reconstruct_r2gs(scene, out, 20, progress=False, fdk=scene.truth, **{**SMALL, "n_gaussians": 100})
    assert res.value_scale == pytest.approx(value_scale_from(scene.truth))
    for f in ("volume.nii.gz", "gaussians.npz", "log.csv", "log.png", "checkpoint.pt", "config.json", "summary.txt"):
        assert (out / f).is_file(), f
    g = np.load(out / "gaussians.npz", allow_pickle=False)
    assert g["means"].shape[0] == res.trainer.n_gaussians
    assert np.allclose(g["densities"] * g["value_scale"], res.trainer.sets[0].to_numpy()["densities"], rtol=1e-5)
    # output in the scan's units: same order of magnitude as the truth
    assert 0.3 < res.volume.max() / scene.truth.max() < 3
    from clgs.io.volume import load_volume
    assert np.allclose(load_volume(out / "volume.nii.gz").volume, res.volume, rtol=1e-6, atol=1e-9)
    from clgs.fit.training_log import TrainingLog
    log = TrainingLog.read_csv(out / "log.csv")
    assert [r["iteration"] for r in log.rows] == [0, 10, 20]
    assert {"psnr3d", "ssim3d", "proj_psnr", "l1", "dssim", "tv", "n_gaussians", "seconds"} <= set(log.columns)
    assert all(20 < r["proj_psnr"] < 60 and 15 < r["psnr3d"] < 60 for r in log.rows)  # sane, in dB
    more = reconstruct_r2gs(scene, out, 30, resume=True, progress=False, fdk=scene.truth)
    assert more.trainer.iteration == 30
    assert [r["iteration"] for r in more.log.rows] == [0, 10, 20, 30]
    with pytest.raises(ValueError, match="drop"):
        reconstruct_r2gs(scene, out, 40, resume=True, progress=False, lambda_tv=0.1)
    with pytest.raises(ckpt.CheckpointError, match="no checkpoint"):
        reconstruct_r2gs(scene, tmp_path / "nothing", 10, resume=True)


def test_early_log_points_and_the_plot_named_by_method(scene, tmp_path, monkeypatch):
    """log_early adds rows at 10, 20, 50, ... below the first log_every (the curve's fast part);
    log.png is titled by the method that ran."""
    from clgs.fit.trainer import early_log_points
    from clgs.fit.training_log import TrainingLog

    assert early_log_points(500) == {10, 20, 50, 100, 200} and early_log_points(10) == set()
    titles = []
    plot = TrainingLog.plot
    monkeypatch.setattr(TrainingLog, "plot",
                        lambda self, path, title="": titles.append(title) or plot(self, path, title))
    for early, rows in ((True, [0, 10, 20, 50, 60]), (False, [0, 60])):
        res = reconstruct_r2gs(scene, tmp_path / str(early), 60, progress=False, fdk=scene.truth,
                               **{**SMALL, "n_gaussians": 100, "log_every": 100, "log_early": early})
        assert [r["iteration"] for r in res.log.rows] == rows
    assert titles == ["R2-Gaussian: 60 iterations"] * 2


def test_each_quality_level_gets_its_own_time(scene):
    """With the default logging (every 500, and early), a short run's quality levels are each
    reached at their own time: a log of the first and last rows alone gave them all one."""
    res = reconstruct_r2gs(scene, None, 200, progress=False, fdk=scene.truth,
                           **{**SMALL, "n_gaussians": 100, "log_every": 500, "log_early": True})
    assert [r["iteration"] for r in res.log.rows] == [0, 10, 20, 50, 100, 200]
    reached = res.log.time_to_quality(step=0.5)
    assert len(reached) >= 3, res.log.rows
    times = [t for _, t, _ in reached]
    assert all(a < b for a, b in zip(times, times[1:])), reached
    assert "linear between the two evaluations" in res.log.summary()


def test_resume_without_iterations_finishes_the_interrupted_run(scene, tmp_path, monkeypatch):
    """An interrupted run resumed with no iterations given ends where it was planned to end, not at
    the 30 000 default; given iterations extend it."""
    from clgs.fit import trainer as T

    out = tmp_path / "run"
    kw = dict(progress=False, fdk=scene.truth, **{**SMALL, "n_gaussians": 100})
    real_step = T.Trainer.step

    def step(self):
        if self.iteration == 12:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(T.Trainer, "step", step)
    first = reconstruct_r2gs(scene, out, 20, **kw)
    assert first.interrupted and first.trainer.iteration == 12
    monkeypatch.setattr(T.Trainer, "step", real_step)
    done = reconstruct_r2gs(scene, out, resume=True, progress=False, fdk=scene.truth)
    assert done.trainer.iteration == 20 and not done.interrupted
    again = reconstruct_r2gs(scene, out, resume=True, progress=False, fdk=scene.truth)
    assert again.trainer.iteration == 20  # finished: nothing more to do
    longer = reconstruct_r2gs(scene, out, 25, resume=True, progress=False, fdk=scene.truth)
    assert longer.trainer.iteration == 25


@pytest.mark.parametrize("kw", [dict(projector_mode="exact"), dict(scale_bounds=None)])
def test_variants_train(scene, kw):
    """The exact ray-integral projector and exp-activated scales run through the same loop."""
    t = _trainer(scene, 40, log_every=0, **kw)
    l1 = [t.step()["l1"] for _ in range(40)]
    assert np.isfinite(l1).all() and np.mean(l1[-5:]) < np.mean(l1[:5])


def test_two_sets_only_the_free_one_densifies(scene, tmp_path):
    """The shape-guided method's layout: a second, non-densified set with its own schedules
    (one parameter frozen), rendered together with the free set; checkpoints hold both."""
    from clgs.fit.gaussians import GaussianSet, Schedule, r2gs_schedules

    t = _trainer(scene, 30, tmp_path, densify_start=5, densify_interval=5)
    rng = np.random.default_rng(1)
    sched = {**r2gs_schedules(30), "means": Schedule(0.1, 0.001, 10, start=10, frozen_before_start=True)}
    fixed = GaussianSet(rng.uniform(-0.3, 0.3, (40, 3)), np.full((40, 3), 0.1), np.tile([1.0, 0, 0, 0], (40, 1)),
                        np.full(40, 0.2), box=t.sets[0].box, schedules=sched, densify=False, name="shape")
    t.sets.append(fixed)
    t._build_optimizer()
    m0 = fixed.params["means"].detach().clone()
    seen = []
    t.hooks.append(type("H", (), {"on_iteration": lambda self, tr: seen.append(
        (len(tr.sets[0]), len(tr.sets[1]), torch.equal(tr.sets[1].params["means"], m0)))})())
    t.fit()
    assert all(n == 40 for _, n, _ in seen) and seen[-1][0] != 150  # only the free set changed size
    assert all(same for _, _, same in seen[:10]) and not seen[-1][2]  # frozen for 10 iterations
    assert t.scene_tensors()[0].shape[0] == len(t.sets[0]) + 40
    back = _trainer(scene, 30, tmp_path)
    back.sets.append(GaussianSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), raw=True,
                                 box=t.sets[0].box, schedules=sched, densify=False, name="shape"))
    back.load_state_dict(ckpt.load(tmp_path / "checkpoint.pt"))
    _same_state(t, back)


def test_cl_backend_voxelizes_only_the_gaussians_that_reach_a_block():
    """The OpenCL backend culls Gaussians by a 3 max(scale) cube before building precisions: a
    block is bitwise the same region of the full grid, and field and gradients match the op fed
    every Gaussian (float64)."""
    from clgs.fit.trainer import Backend
    from clgs.geometry import Grid
    from clgs.ops.voxelizer import _GridField, cov_prec, default_voxelizer

    g = torch.Generator().manual_seed(3)
    n = 400
    means = ((torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.9).requires_grad_(True)
    scales = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.06 + 0.01).requires_grad_(True)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64).requires_grad_(True)
    dens = (torch.rand(n, generator=g, dtype=torch.float64) + 0.1).requires_grad_(True)
    params = (means, scales, quats, dens)
    grid = Grid((20, 21, 22), (-1.0, -1.0, -1.0), (0.095, 0.095, 0.095))
    block = grid.block((4, 6, 8), (7, 6, 5))
    be = Backend("cl")
    with torch.no_grad():  # float32, as trained: the block is bitwise the full grid's region
        p32 = [t.detach().float() for t in params]
        assert torch.equal(be.voxelize(*p32, block), be.voxelize(*p32, grid)[4:11, 6:12, 8:13])
    part = be.voxelize(*params, block)
    assert float(part.detach().abs().max()) > 0
    cov, prec, _ = cov_prec(scales, quats)
    extent = 3.0 * torch.sqrt(cov.detach()[:, [0, 3, 5]])
    whole = _GridField.apply(means, prec, dens, extent, block, default_voxelizer())
    torch.testing.assert_close(part, whole, rtol=1e-13, atol=0)
    w = torch.rand(block.shape, generator=g, dtype=torch.float64)
    for a, b in zip(torch.autograd.grad((part * w).sum(), params),
                    torch.autograd.grad((whole * w).sum(), params)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


def test_cl_backend_shares_the_projections_matrices_with_the_tv_patch():
    """In a training step the projection builds covariance, precision and half-widths of every
    Gaussian in one kernel and the patch reuses them (same tensors): the field is bitwise the one
    built from scratch, the gradients through both paths agree (float64), and the kept matrices
    are dropped by ``forget`` (or ignored once the tensors change)."""
    from clgs.fit.trainer import Backend
    from clgs.geometry import Geometry

    geo = Geometry.default(n_views=4, n_voxel=24, n_detector=32, volume_mm=64.0)
    g = torch.Generator().manual_seed(5)
    n = 300
    means = ((torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.8).requires_grad_(True)
    scales = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.05 + 0.02).requires_grad_(True)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64).requires_grad_(True)
    dens = (torch.rand(n, generator=g, dtype=torch.float64) + 0.1).requires_grad_(True)
    params = (means, scales, quats, dens)
    block = geo.volume_grid(scene=True).block((3, 5, 7), (10, 9, 8))
    wb = torch.rand(block.shape, generator=g, dtype=torch.float64)

    be = Backend("cl")
    proj = be.project(*params, geo, [1])
    assert be._last is not None
    shared = be.voxelize(*params, block)
    grads = torch.autograd.grad(proj.sum() + (shared * wb).sum(), params)
    be.forget()
    assert be._last is None
    alone = Backend("cl")
    proj2 = alone.project(*params, geo, [1])
    alone.forget()
    fresh = alone.voxelize(*params, block)  # culls by 3 max(scale), builds the precisions itself
    assert float(fresh.detach().abs().max()) > 0
    assert torch.equal(shared.detach(), fresh.detach())
    for a, b in zip(grads, torch.autograd.grad(proj2.sum() + (fresh * wb).sum(), params)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-13)
    # changed in place: the kept matrices are stale and must not be used
    be.project(*params, geo, [1])
    with torch.no_grad():
        scales.mul_(1.5)
    torch.testing.assert_close(be.voxelize(*params, block), Backend("cl").voxelize(*params, block), rtol=0, atol=0)


def test_iterations_leave_no_context_behind(scene):
    """Each iteration's context (render, gradient hook) is freed: nothing piles up over a run."""
    import gc

    from clgs.fit.trainer import Context

    t = _trainer(scene, 5)
    t.fit()
    gc.collect()
    assert sum(type(o) is Context for o in gc.get_objects()) == 0


def test_scale_floor_follows_the_scans_resolution():
    """The smallest scale is 0.4 x the finer of voxel and axis-pixel size, never below the extent's
    0.05 %; a floor above the largest scale is a clear error."""
    from clgs.fit.assembly import scale_bounds_for

    geo = Geometry.default(n_views=4, n_voxel=64, n_detector=128, volume_mm=256.0)
    pixel_at_axis = geo.dDetector[0] * geo.DSO / geo.DSD
    assert geo.resolution_mm == pytest.approx(min(4.0, pixel_at_axis))
    lo, hi = scale_bounds_for(geo, (0.0005, 0.5), 0.4)
    assert lo == pytest.approx(0.4 * geo.resolution_mm / 256.0) and hi == 0.5
    assert lo > 9 * 0.0005  # the old floor was 1/30 of a voxel here
    assert scale_bounds_for(geo, (0.0005, 0.5), None) == (0.0005, 0.5)
    assert scale_bounds_for(geo, (0.01, 0.5), 0.4)[0] == 0.01  # the larger of the two wins
    assert scale_bounds_for(geo, None, 0.4) is None
    with pytest.raises(ValueError, match="lower scale_floor"):
        scale_bounds_for(geo, (0.0005, 0.002), 0.4)


def test_trained_scales_respect_the_floor(scene):
    from clgs.fit.assembly import scale_bounds_for

    t = _trainer(scene, 30, scale_floor=0.4)
    t.fit()
    lo = scale_bounds_for(scene.geometry, (0.0005, 0.5), 0.4)[0] * t.sets[0].extent
    assert t.sets[0].scale_range[0] == pytest.approx(lo) and lo > 0.0005 * t.sets[0].extent
    assert float(t.sets[0].tensors()[1].detach().min()) >= lo * (1 - 1e-6)


def test_resume_of_a_checkpoint_without_a_floor_keeps_its_bounds(scene, tmp_path):
    """Checkpoints written before ``scale_floor`` existed resume with the bounds they trained with."""
    from clgs.fit.config import run_config

    t = _trainer(scene, 12, tmp_path, scale_floor=None)
    t.fit()
    state = ckpt.load(tmp_path / "checkpoint.pt")
    saved = ckpt.loads(state["config"])
    saved.pop("scale_floor")
    state["config"] = ckpt.dumps(saved)
    ckpt.save(tmp_path / "checkpoint.pt", state)
    cfg, _ = run_config(R2GSConfig, 12, {}, True, tmp_path)
    assert cfg.scale_floor is None


def test_non_finite_parameters_stop_the_run_and_keep_the_last_good_checkpoint(scene, tmp_path):
    """The kernels skip NaN Gaussians, so the loss can stay finite while the model breaks: the
    trainer checks the parameters and never writes a broken checkpoint."""
    from clgs.fit import trainer as T

    class Poison:
        def on_iteration(self, trainer):
            if trainer.iteration == 33:  # after densification ends (it would prune a NaN Gaussian)
                with torch.no_grad():
                    trainer.sets[0].params["scales"][3, 1] = float("nan")

    t = _trainer(scene, 60, tmp_path, checkpoint_every=10)
    t.hooks.append(Poison())
    with pytest.raises(FloatingPointError, match=r"free\.scales.* became NaN or Inf by iteration 40.*last checkpoint"):
        t.fit()
    state = ckpt.load(tmp_path / "checkpoint.pt")
    assert state["iteration"] == 30  # the last good one, not overwritten
    assert all(torch.isfinite(v).all() for v in state["sets"]["free"].values() if torch.is_tensor(v))
    assert T.FINITE_CHECK_EVERY <= 100  # a broken run stops within this many iterations


def test_broken_or_foreign_checkpoints_are_refused(scene, tmp_path):
    t = _trainer(scene, 10, tmp_path)
    t.fit()
    good = ckpt.load(tmp_path / "checkpoint.pt")

    def resume_with(state):
        path = tmp_path / "edited.pt"
        ckpt.save(path, state)
        _trainer(scene, 10).resume(path)

    bad = dict(good, sets={k: dict(v) for k, v in good["sets"].items()})
    bad["sets"]["free"]["means"] = bad["sets"]["free"]["means"].clone()
    bad["sets"]["free"]["means"][0, 0] = float("inf")
    with pytest.raises(ckpt.CheckpointError, match=r"free\.means hold NaN or Inf"):
        resume_with(bad)
    with pytest.raises(ckpt.CheckpointError, match="lacks optimizer"):
        resume_with({k: v for k, v in good.items() if k != "optimizer"})
    with pytest.raises(ckpt.CheckpointError, match="iteration must be >= 0"):
        resume_with(dict(good, iteration=-5))
    other = Scan(scene.geometry, scene.projections * 1.01, scene.truth)
    with pytest.raises(ckpt.CheckpointError, match="other projections or another scan geometry"):
        build_trainer(other, _cfg(10, init="random", value_scale=60.0)).resume(tmp_path / "checkpoint.pt")
    resume_with(good)  # the untouched one still loads


@pytest.mark.parametrize("setting,message", [
    (dict(value_scale=-1), "value_scale must be > 0"), (dict(n_gaussians=0), "n_gaussians must be >= 1"),
    (dict(iterations="abc"), "iterations must be a number"), (dict(iterations=2.5), "whole number"),
    (dict(backend="gpu"), "backend must be one of cl, torch"), (dict(seed=-1), "seed must be >= 0"),
    (dict(densify_interval=0), "densify_interval must be >= 1"), (dict(lambda_tv=float("inf")), "finite"),
    (dict(scale_bounds=[0.5, 0.1]), "0 < low < high"), (dict(lambda_dssim=True), "must be a number"),
])
def test_settings_of_the_wrong_kind_or_range_are_refused(setting, message):
    with pytest.raises(ValueError, match=f"r2gs setting .*{message}"):
        R2GSConfig.from_json(setting)


def test_shape_guided_settings_are_checked_too():
    from clgs.methods.shape_guided import ShapeGuidedConfig

    with pytest.raises(ValueError, match="shape_prior must be true or false"):
        ShapeGuidedConfig.from_json({"shape_prior": "yes"})
    with pytest.raises(ValueError, match="tau must be > 0"):
        ShapeGuidedConfig.from_json({"tau": 0})
    with pytest.raises(ValueError, match="lr_alpha must be >= 0"):
        ShapeGuidedConfig.from_json({"lr_alpha": -1})
    assert ShapeGuidedConfig.from_json({"iterations": 1e3}).iterations == 1000  # JSON's 1e3 is a count


def test_an_os_sart_start_places_the_gaussians_on_the_sart_volume(scene):
    """``init="sart"``: the start volume (and the value scale from it) is OS-SART's, 10 iterations
    of 5 subsets unless told otherwise; the FDK is not computed."""
    from clgs.ct.sart import sart
    from clgs.methods import r2gs

    ref = sart(scene.projections, scene.geometry, n_iter=3, subsets=5)
    cfg = R2GSConfig(**{**SMALL, "iterations": 5, "init": "sart", "init_sart_iterations": 3, "n_gaussians": 80})
    t = build_trainer(scene, cfg)
    assert cfg.value_scale == pytest.approx(value_scale_from(ref), rel=1e-6)
    assert 0 < t.n_gaussians <= 80
    with pytest.raises(Exception, match="init must be one of fdk, sart, random"):
        R2GSConfig(init="art")
    assert r2gs.sart_start(scene, 3).shape == tuple(scene.geometry.nVoxel)
