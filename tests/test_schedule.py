"""Schedules (clgs.fit.schedule): the fast and paper settings a run gets, the plateau rule that
ends a fast run, which never reads the truth, and a stopped or interrupted fast run that resumes
bit for bit."""
import numpy as np
import pytest
import torch
from gaussian_scene import six_gaussian_scan

from clgs.errors import InputError
from clgs.fit import checkpoint as ckpt
from clgs.fit.config import run_config
from clgs.fit.schedule import PAPER_ITERATIONS, PlateauStop, resolve, views_loss
from clgs.geometry import Geometry
from clgs.io.scan import Scan
from clgs.methods.r2gs import R2GSConfig, build_trainer, reconstruct_r2gs
from clgs.methods.shape_guided import ShapeGuidedConfig


@pytest.fixture(scope="module")
def scene():
    """6 Gaussians in a 64 mm cube, 8 cone-beam views (as tests/test_trainer.py's)."""
    return six_gaussian_scan()


# a fast run short enough for a test: densification early, plateau checks every 10 iterations after it
FAST = dict(n_gaussians=120, max_gaussians=400, init="random", value_scale=60.0, log_every=10, checkpoint_every=0,
            densify_start=10, densify_interval=10, densify_until=60, stop_every=10, stop_tolerance=0.1,
            stop_patience=2)


# ---------------------------------------------------------------------- what a run gets
def test_paper_keeps_the_published_schedule():
    d = resolve(R2GSConfig, None, {"schedule": "paper"})
    assert d["iterations"] == PAPER_ITERATIONS == 30_000
    assert (d["densify_start"], d["densify_until"], d["densify_interval"]) == (500, 15_000, 100)
    assert d["stop_every"] == 0 and d["schedule"] == "paper"
    # given iterations shorten it; the decays follow the run (as before schedules existed)
    cfg, _ = run_config(R2GSConfig, 1000, {"schedule": "paper"}, False, None)
    assert cfg.iterations == 1000 and cfg.densify_until == 15_000 and not cfg.stop_every


@pytest.mark.parametrize("config", [R2GSConfig, ShapeGuidedConfig])
def test_fast_is_the_default_and_cuts_the_paper_short(config):
    """The fast schedule is the paper's run cut short: the same learning rates and densification
    at every iteration it runs, fewer iterations, the plateau rule on."""
    cfg, _ = run_config(config, None, {}, False, None)
    paper, _ = run_config(config, None, {"schedule": "paper"}, False, None)
    n = config.FAST_ITERATIONS
    assert cfg.schedule == "fast" and cfg.iterations == n < PAPER_ITERATIONS
    assert cfg.schedule_iterations == PAPER_ITERATIONS  # the decays of the 30 000-iteration run
    same = ("densify_start", "densify_until", "densify_interval", "grad_threshold", "lambda_tv", "lambda_dssim")
    assert all(getattr(cfg, k) == getattr(paper, k) for k in same)
    assert cfg.stop_every == config.FAST_STOP_EVERY and paper.stop_every == 0
    # the shape-guided method's fast runs stop at a plateau; R2-Gaussian mode's run to their end
    # (its projection loss plateaus while the volume still improves: docs/schedules.md)
    assert (ShapeGuidedConfig.FAST_STOP_EVERY > 0) and R2GSConfig.FAST_STOP_EVERY == 0
    longer, _ = run_config(config, 50_000, {}, False, None)
    assert longer.schedule_iterations == 50_000  # more than the paper's: the decays span the run


def test_what_is_given_wins_over_the_schedule():
    cfg, _ = run_config(R2GSConfig, 3000, {"densify_until": 2500, "stop_every": 0}, False, None)
    assert cfg.iterations == 3000 and cfg.densify_until == 2500 and cfg.stop_every == 0
    assert cfg.densify_start == 500 and cfg.schedule_iterations == PAPER_ITERATIONS
    cfg, _ = run_config(R2GSConfig, 3000, {"schedule_iterations": 3000}, False, None)
    assert cfg.schedule_iterations == 3000  # the paper's compression, asked for
    with pytest.raises(InputError, match="schedule must be one of fast, paper"):
        run_config(R2GSConfig, None, {"schedule": "slow"}, False, None)


def test_lr_factor_reaches_the_optimiser(scene):
    """``lr_factor`` multiplies every learning rate the R2-Gaussian trainer's Adam steps with, and
    is refused at 0 (a run that cannot move)."""
    def rates(factor):
        t = build_trainer(scene, R2GSConfig(**{**FAST, "iterations": 5, "lr_factor": factor}))
        return {g["name"]: g["lr"] for g in t.optimizer.param_groups}

    one, three = rates(1.0), rates(3.0)
    assert set(one) == set(three) and len(one) == 4
    for name, lr in one.items():
        assert three[name] == pytest.approx(3 * lr)
    with pytest.raises(InputError, match="lr_factor"):
        run_config(R2GSConfig, None, {"lr_factor": 0}, False, None)
    # a shape-guided run's free means take it too (the other free rates come from the same schedules)
    from clgs.methods.shape_guided import shape_schedules

    base = shape_schedules(ShapeGuidedConfig(), 1000, free_means=True)["means"]
    tripled = shape_schedules(ShapeGuidedConfig(lr_factor=3.0), 1000, free_means=True)["means"]
    assert tripled(0) == pytest.approx(3 * base(0)) and tripled(1000) == pytest.approx(3 * base(1000))


def test_a_methods_fast_settings_apply_to_fast_runs_only_and_given_settings_win(monkeypatch):
    monkeypatch.setattr(R2GSConfig, "FAST_SETTINGS", {"tv_every": 4})
    assert run_config(R2GSConfig, None, {}, False, None)[0].tv_every == 4
    assert run_config(R2GSConfig, None, {"schedule": "paper"}, False, None)[0].tv_every == 1
    assert run_config(R2GSConfig, None, {"tv_every": 2}, False, None)[0].tv_every == 2


# ---------------------------------------------------------------------- the plateau rule
class _Loss:
    """A trainer stand-in whose views_loss follows a given list (through the monkeypatch below)."""

    def __init__(self, iterations=1000):
        self.iteration, self.iterations, self.stopped = 0, iterations, None

    def request_stop(self, info):
        self.stopped = info


def test_plateau_stops_after_patience_flat_checks(monkeypatch):
    from clgs.fit import schedule as S

    losses = iter([1.0, 0.5, 0.3, 0.299, 0.2985, 0.2])
    monkeypatch.setattr(S, "views_loss", lambda trainer: next(losses))
    rule, t = PlateauStop(every=10, tolerance=0.01, patience=2, after=10), _Loss()
    for it in range(1, 80):
        t.iteration = it
        rule.on_iteration(t)
        if t.stopped:
            break
    # checks at 10 (1.0), 20 (0.5), 30 (0.3), 40 (0.299: flat 1), 50 (0.2985: flat 2 -> stop)
    assert t.stopped["iteration"] == 50
    assert rule.state_dict()["flat"] == 2
    with pytest.raises(InputError):
        PlateauStop(every=10, tolerance=float("nan"))


def test_a_fall_between_flat_checks_starts_the_count_again(monkeypatch):
    from clgs.fit import schedule as S

    losses = iter([1.0, 0.999, 0.5, 0.499, 0.4])
    monkeypatch.setattr(S, "views_loss", lambda trainer: next(losses))
    rule, t = PlateauStop(every=1, tolerance=0.01, patience=2), _Loss()
    for it in range(1, 6):
        t.iteration = it
        rule.on_iteration(t)
    assert t.stopped is None  # flat, fall, flat, fall: never two flat in a row


def test_views_loss_is_the_mean_l1_over_every_view(scene):
    t = build_trainer(scene, R2GSConfig(**{**FAST, "iterations": 5}))
    with torch.no_grad():
        tensors = tuple(x.detach() for x in t.scene_tensors())
        ref = torch.stack([t.backend.project(*tensors, t.geometry, [v])[0] * t.render_scale for v in t.views])
    expected = float((ref - t.projections).abs().mean())
    assert views_loss(t) == pytest.approx(expected, rel=1e-5)


def _fast_run(scan, out=None, iterations=200, **kw):
    return reconstruct_r2gs(scan, out, iterations, progress=False, fdk=scan.truth if scan.truth is not None else None,
                            **{**FAST, **kw})


def test_a_fast_run_stops_when_converged_and_the_truth_plays_no_part(scene):
    """The stop comes from the projections alone: the same scan with its truth, a wrong truth and
    no truth stops at the same iteration with the same Gaussians."""
    runs = []
    fdk = scene.truth
    for truth in (scene.truth, np.random.default_rng(1).random(scene.truth.shape).astype(np.float32), None):
        s = Scan(scene.geometry, scene.projections, truth)
        runs.append(reconstruct_r2gs(s, None, 200, progress=False, fdk=fdk, **FAST))
    first = runs[0].trainer
    assert first.converged is not None and first.iteration < 200, "the plateau rule never fired"
    assert first.iteration == first.converged["iteration"] >= first.config["densify_until"] == 60
    assert not runs[0].interrupted
    for other in runs[1:]:
        assert other.trainer.iteration == first.iteration
        for k in first.sets[0].params:
            assert torch.equal(first.sets[0].params[k], other.trainer.sets[0].params[k]), k


def test_a_converged_run_resumed_does_nothing_more(scene, tmp_path):
    out = tmp_path / "run"
    done = _fast_run(scene, out)
    it = done.trainer.iteration
    assert done.trainer.converged is not None and it < 200
    state = ckpt.load(out / "checkpoint.pt")
    assert ckpt.loads(state["converged"])["iteration"] == it
    again = reconstruct_r2gs(scene, out, resume=True, progress=False, fdk=scene.truth)
    assert again.trainer.iteration == it and again.trainer.converged == done.trainer.converged


def test_an_interrupted_fast_run_resumes_bit_for_bit(scene, tmp_path, monkeypatch):
    """Interrupted after the plateau checks began (their history is in the checkpoint), resumed:
    the same stop, the same Gaussians, Adam moments and log as the run that was never stopped."""
    from clgs.fit import trainer as T

    whole = _fast_run(scene).trainer
    stop_at = whole.converged["iteration"] - 5  # between its last two checks
    real_step = T.Trainer.step

    def step(self):
        if self.iteration == stop_at:
            raise KeyboardInterrupt
        return real_step(self)

    out = tmp_path / "run"
    monkeypatch.setattr(T.Trainer, "step", step)
    first = _fast_run(scene, out)
    assert first.interrupted and first.trainer.iteration == stop_at and first.trainer.converged is None
    monkeypatch.setattr(T.Trainer, "step", real_step)
    resumed = reconstruct_r2gs(scene, out, resume=True, progress=False, fdk=scene.truth).trainer
    assert resumed.iteration == whole.iteration and resumed.converged == whole.converged
    for k in whole.sets[0].params:
        assert torch.equal(whole.sets[0].params[k], resumed.sets[0].params[k]), k
    oa, ob = whole.optimizer.state_dict(), resumed.optimizer.state_dict()
    for i in oa["state"]:
        for k in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(oa["state"][i][k], ob["state"][i][k]), (i, k)
    strip = lambda rows: [{k: v for k, v in r.items() if k not in ("seconds", "wall")} for r in rows]  # noqa: E731
    assert strip(whole.log.rows) == strip(resumed.log.rows)


def test_old_checkpoints_resume_on_the_paper_schedule(scene, tmp_path):
    out = tmp_path / "run"
    _fast_run(scene, out, iterations=12, stop_every=0)
    state = ckpt.load(out / "checkpoint.pt")
    saved = ckpt.loads(state["config"])
    for key in ("schedule", "stop_every", "stop_tolerance", "stop_patience"):
        saved.pop(key)
    state["config"] = ckpt.dumps(saved)
    state.pop("converged")
    ckpt.save(out / "checkpoint.pt", state)
    cfg, _ = run_config(R2GSConfig, None, {}, True, out)
    assert cfg.schedule == "paper" and cfg.stop_every == 0


# ---------------------------------------------------------------------- coarse-to-fine
@pytest.mark.parametrize("vectors", [False, True])
def test_the_binned_detector_sees_the_binned_projections(scene, vectors):
    """Projections rendered on the 2x2-binned detector match the full detector's averaged over
    2x2 blocks (a coarse pixel's centre sample against its four fine samples: close, not equal),
    for a circular and a per-view geometry; and a detector that does not divide is refused."""
    from clgs.fit.schedule import bin_projections
    from clgs.geometry import GeometryError
    from clgs.ops.projector import project

    geo = Geometry.default(n_views=4, n_voxel=16, n_detector=48, volume_mm=64.0)
    geo = geo.as_vectors() if vectors else geo
    rng = np.random.default_rng(2)
    m = torch.tensor(rng.uniform(-0.3, 0.3, (5, 3)), dtype=torch.float32)
    s = torch.tensor(rng.uniform(0.15, 0.3, (5, 3)), dtype=torch.float32)
    q = torch.tensor(rng.normal(size=(5, 4)), dtype=torch.float32)
    d = torch.full((5,), 0.02)
    views = list(range(4))
    with torch.no_grad():
        fine = project(m, s, q, d, geo, views)
        coarse = project(m, s, q, d, geo.binned(2), views)
    binned = bin_projections(fine, 2)
    assert coarse.shape == binned.shape == (4, 24, 24)
    assert float((coarse - binned).abs().max()) < 0.03 * float(binned.max())
    assert float((coarse - binned).abs().mean()) < 0.003 * float(binned.max())
    assert geo.binned(1) is geo
    with pytest.raises(GeometryError, match="multiples"):
        Geometry.default(n_views=2, n_detector=25).binned(2)


def test_coarse_to_fine_trains_coarse_then_full_and_resumes_bit_for_bit(scene, tmp_path, monkeypatch):
    from clgs.fit import trainer as T

    kw = dict(FAST, coarse_until=0.5, stop_every=0)
    whole = _fast_run(scene, iterations=40, **kw).trainer
    assert tuple(whole.geometry.nDetector) == tuple(scene.geometry.nDetector)  # full resolution at the end
    first_row = whole.log.rows[0]
    assert first_row["iteration"] == 0
    real_step = T.Trainer.step
    seen = []

    def step(self):
        seen.append(tuple(self.projections.shape[1:]))
        if self.iteration == 13 and not (tmp_path / "run" / "checkpoint.pt").exists():
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(T.Trainer, "step", step)
    first = _fast_run(scene, tmp_path / "run", iterations=40, **kw)
    assert first.interrupted and seen[0] == (12, 12)
    resumed = reconstruct_r2gs(scene, tmp_path / "run", resume=True, progress=False, fdk=scene.truth).trainer
    # the step at iteration 13 ran twice (interrupted, then resumed): iteration i is seen[i + 1] from there
    assert seen[14] == seen[20] == (12, 12) and seen[21] == seen[-1] == (24, 24) and len(seen) == 41
    for k in whole.sets[0].params:
        assert torch.equal(whole.sets[0].params[k], resumed.sets[0].params[k]), k


# ---------------------------------------------------------------------- TV every k-th iteration
def test_tv_every_k_runs_the_patch_on_every_kth_iteration_weighted_k(scene):
    """``tv_every=k``: the TV term is k times the TV patch on iterations divisible by k (drawn from
    the same random block as a k=1 term with the same generator state) and absent on the others;
    a run trains only those iterations' TV (the log's TV is the mean over every iteration)."""
    from types import SimpleNamespace

    from clgs.fit.assembly import tv_term
    from clgs.fit.trainer import Backend

    t = build_trainer(scene, R2GSConfig(**{**FAST, "iterations": 5}))
    tensors = tuple(x.detach() for x in t.scene_tensors())

    def ctx(it, seed=3):
        return SimpleNamespace(iteration=it, geometry=t.geometry, generator=torch.Generator().manual_seed(seed),
                               trainer=SimpleNamespace(backend=Backend("cl")), tensors=tensors)

    every3, every1 = tv_term(8, 3), tv_term(8, 1)
    for it in (1, 2, 4, 5):
        assert every3(ctx(it)) is None
    for it in (0, 3, 6):
        one = float(every1(ctx(it)))
        assert one > 0 and float(every3(ctx(it))) == pytest.approx(3 * one, rel=1e-6)
    # in a run: the term is in the step's values on iterations 0, 3, 6, ... only
    t = build_trainer(scene, R2GSConfig(**{**FAST, "iterations": 7, "tv_every": 3, "lambda_tv": 0.05}))
    seen = []
    for _ in range(7):
        it = t.iteration
        seen.append((it, "tv" in t.step()))
    assert seen == [(i, i % 3 == 0) for i in range(7)]
    with pytest.raises(InputError, match="tv_every"):
        R2GSConfig(tv_every=0)


def test_many_view_scans_get_four_views_a_step_under_the_fast_schedule_only():
    """On 20 views or more R2-Gaussian mode's fast run takes 6 000 steps of four views at twice the
    learning rates (docs/schedules.md); fewer views, the paper's schedule, the shape-guided method
    and settings given keep theirs."""
    def run(config=R2GSConfig, n=25, iterations=None, **kw):
        cfg, _ = run_config(config, iterations, kw, False, None, n_views=n)
        return cfg.iterations, cfg.views_per_step, cfg.lr_factor

    assert run(n=25) == run(n=20) == (6000, 4, 2.0)
    assert run(n=19) == run(n=5) == run(n=None) == (R2GSConfig.FAST_ITERATIONS, 1, 1.0)
    assert run(n=25, schedule="paper") == (30_000, 1, 1.0)
    assert run(n=25, iterations=3000) == (3000, 4, 2.0)
    assert run(n=25, views_per_step=1, lr_factor=1.0) == (6000, 1, 1.0)
    assert run(ShapeGuidedConfig, n=25)[1:] == (1, 1.0)


def test_a_many_view_run_trains_and_records_its_views_per_step(scene, tmp_path, monkeypatch):
    import json

    monkeypatch.setattr(R2GSConfig, "MANY_VIEWS", scene.geometry.n_views)  # this 8-view scene counts as many
    res = reconstruct_r2gs(scene, tmp_path / "run", 4, progress=False, fdk=scene.truth, **FAST)
    assert res.trainer.views_per_step == 4
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["views_per_step"] == 4 and saved["lr_factor"] == 2.0
    again = reconstruct_r2gs(scene, tmp_path / "run", resume=True, progress=False, fdk=scene.truth)
    assert again.trainer.views_per_step == 4
    from clgs.methods.r2gs import run_method  # what report.json's "info" says of the run

    info = run_method(scene, None, 2, progress=False, fdk=scene.truth, **FAST)["info"]
    assert (info["iterations"], info["views_per_step"], info["lr_factor"]) == (2, 4, 2.0)


def test_too_many_views_per_step_is_refused_before_the_start_is_computed(scene, monkeypatch):
    """More views a step than the scan has stops with the reason before any FDK is computed."""
    import clgs.methods.r2gs as r2gs

    def no_fdk(*a, **k):
        raise AssertionError("the FDK start was computed for a refused setting")

    monkeypatch.setattr(r2gs, "fdk_volume", no_fdk)
    with pytest.raises(InputError, match="views_per_step must be between 1 and the 8 training views, got 9"):
        reconstruct_r2gs(scene, None, 2, progress=False, views_per_step=9)
