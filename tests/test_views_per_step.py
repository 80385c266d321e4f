"""Several views per iteration (``views_per_step``): the projection terms of the step's views
averaged against single-view gradients computed by hand, one TV patch per step, the densification
statistic of each view as if it had had its own step, the bounds, and a bit-for-bit resume."""
import numpy as np
import pytest
import torch
from gaussian_scene import six_gaussian_scan

from clgs.errors import InputError
from clgs.fit import checkpoint as ckpt
from clgs.fit.trainer import Context
from clgs.methods.r2gs import R2GSConfig, build_trainer

SMALL = dict(n_gaussians=150, densify_start=10, densify_interval=10, densify_until=30, log_every=10,
             checkpoint_every=0, max_gaussians=600)


@pytest.fixture(scope="module")
def scene():
    return six_gaussian_scan()  # 8 cone-beam views


def _trainer(scene, iterations, out=None, **kw):
    cfg = R2GSConfig(**{**SMALL, "iterations": iterations, "init": "random", "value_scale": 60.0, **kw})
    return build_trainer(scene, cfg, out)


def _params(t):
    return [p for g in t.optimizer.param_groups for p in g["params"]]


def _single_view_grads(t, view):
    """The gradient of ``view``'s projection terms alone (what a one-view step would follow)."""
    for p in _params(t):
        p.grad = None
    ctx = Context(t, view)
    total = sum(term.weight * term.fn(ctx) for term in t.losses if term.per_view and term.weight)
    total.backward()
    out = [p.grad.detach().clone() for p in _params(t)]
    for p in _params(t):
        p.grad = None
    return float(total.detach()), out


def _grads_of_one_step(t, views):
    """Run one step drawing ``views`` (in this order) and return (values, gradients before Adam)."""
    seen = []

    class Grab:
        def after_backward(self, trainer, ctx):
            seen.append(([c.view for c in ctx.group], [p.grad.detach().clone() for p in _params(trainer)]))

    t.hooks.append(Grab())
    t.view_stack = list(reversed(views))  # views are popped from the end
    values = t.step()
    t.hooks.pop()
    (drawn, grads), = seen
    assert drawn == list(views)
    return values, grads


def test_a_step_of_several_views_follows_their_mean_gradient(scene):
    """With three views the step's projection loss is the mean of the three views' own losses and
    its gradient the mean of their gradients (each computed alone, by hand)."""
    views = [0, 3, 6]
    ref = _trainer(scene, 5, lambda_tv=0.0)
    singles = [_single_view_grads(ref, v) for v in views]
    t = _trainer(scene, 5, lambda_tv=0.0, views_per_step=3)
    values, grads = _grads_of_one_step(t, views)
    mean_loss = sum(s[0] for s in singles) / 3
    assert values["loss"] == pytest.approx(mean_loss, rel=1e-5)
    moving = 0
    for i, g in enumerate(grads):
        want = sum(s[1][i] for s in singles) / 3
        moving += float(want.abs().max()) > 0
        torch.testing.assert_close(g, want, rtol=1e-4, atol=1e-6 * float(want.abs().max()))
    assert moving >= 3  # means, scales, densities at least
    # and not the first view's alone: the test can tell them apart
    assert not torch.allclose(grads[0], singles[0][1][0], rtol=1e-3, atol=0)


def test_one_tv_patch_per_step(scene, monkeypatch):
    import clgs.fit.tv_patch

    calls = []
    tv = clgs.fit.tv_patch.patch_tv
    monkeypatch.setattr(clgs.fit.tv_patch, "patch_tv", lambda backend, tensors, grid: calls.append(grid.shape)
                        or tv(backend, tensors, grid))
    t = _trainer(scene, 4, lambda_tv=0.05, views_per_step=4)
    t.evaluate = None
    renders, built = [], []
    scene_tensors = t.scene_tensors
    t.scene_tensors = lambda: built.append(1) or scene_tensors()
    project = t.backend.project
    t.backend.project = lambda *a: renders.append(list(a[-1])) or project(*a)
    t.fit()
    assert len(calls) == 4  # one patch per iteration
    assert len(built) == 4  # the Gaussians' activations once a step, for its four views and the patch
    assert len(renders) == 16 and all(len(r) == 1 for r in renders)  # four views per iteration
    assert sorted(v for r in renders[:8] for v in r) == list(range(8))  # each view once per pass over them


def test_each_view_adds_its_own_densification_statistic(scene):
    """The statistic after a two-view step is the sum of the two views' statistics, each as a
    one-view step from the same state gives it (the step's 1/2 weight undone), seen twice."""
    def stats(views, k):
        t = _trainer(scene, 5, lambda_tv=0.0, views_per_step=k)
        if k == 1:
            t.view_stack = list(reversed(views))
        else:
            _grads_of_one_step(t, views)
            return next(h for h in t.hooks if hasattr(h, "stats")).stats["free"]
        t.step()
        return next(h for h in t.hooks if hasattr(h, "stats")).stats["free"]

    (a, ca), (b, cb) = stats([1], 1), stats([5], 1)
    acc, cnt = stats([1, 5], 2)
    assert float(a.sum()) > 0 and float(b.sum()) > 0
    torch.testing.assert_close(acc, a + b, rtol=1e-4, atol=1e-6 * float((a + b).max()))
    assert torch.equal(cnt, ca + cb)


def test_a_step_draws_distinct_views_across_passes(scene):
    """Three views a step over eight: a step that runs past a pass's end takes the rest of it and
    then only views it does not hold; over the run every view comes once per pass (counted over
    whole passes), and one view a step draws the plain pass-by-pass shuffle."""
    t = _trainer(scene, 2, views_per_step=3)
    steps = [t.next_views(3) for _ in range(40)]  # 120 views: 15 passes of 8
    assert all(len(set(s)) == 3 for s in steps)
    flat = [v for s in steps for v in s]
    for p in range(15):
        assert sorted(flat[8 * p:8 * p + 8]) == list(range(8))
    # the one view left of a pass is the one the next shuffle would draw first: a plain refill
    # would repeat it within the step
    leftover = int(np.random.default_rng(0).permutation(8)[-1])
    t.rng, t.view_stack = np.random.default_rng(0), [leftover]
    got = t.next_views(3)
    assert got[0] == leftover and len(set(got)) == 3
    assert sorted(got[1:] + t.view_stack) == sorted(set(range(8)) - {leftover}) + [leftover]
    one = _trainer(scene, 2)
    plain = np.random.default_rng(0)
    want = [int(v) for _ in range(3) for v in reversed(plain.permutation(8))]
    assert [one.next_views(1)[0] for _ in range(24)] == want


def test_views_per_step_bounds(scene):
    with pytest.raises(ValueError, match="views_per_step must be >= 1"):
        R2GSConfig.from_json({"views_per_step": 0})
    with pytest.raises(InputError, match="views_per_step must be between 1 and the 8 training views, got 9"):
        _trainer(scene, 2, views_per_step=9)


def test_a_multi_view_run_resumes_bit_for_bit(scene, tmp_path):
    kw = dict(views_per_step=3)
    whole = _trainer(scene, 24, **kw).fit()
    first = _trainer(scene, 24, tmp_path, **kw)
    first.iterations = 11
    first.fit()
    resumed = _trainer(scene, 24, tmp_path, **kw)
    resumed.load_state_dict(ckpt.load(tmp_path / "checkpoint.pt"))
    resumed.fit()
    for sa, sb in zip(whole.sets, resumed.sets):
        for k in sa.params:
            assert torch.equal(sa.params[k], sb.params[k]), k
    assert whole.view_stack == resumed.view_stack and whole.n_gaussians == resumed.n_gaussians > 150
