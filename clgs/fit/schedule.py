"""How a Gaussian run spends its iterations: the paper's schedule or the fast one, and the rule
that ends a run once its projections stop improving.

Why: the papers' 30 000 iterations are sized for a GPU. On a CPU a run's quality is bought by the
hour, and the convergence curves (docs/schedules.md) show where it is bought: the shape-guided
femur has 99 % of its gain within the first tenth of the run, and what follows buys nothing (its
3D PSNR peaks at a fifth of the run and slowly falls). Compressing the paper's schedule into a
shorter run (its learning rates decayed sooner) was measured and is worse than cutting the
paper's schedule short: the early, high learning rates are what converge. Two schedules:

* ``paper``: the published settings as they are: 30 000 iterations, the learning-rate decays over
  them, densification from 500 to 15 000 every 100, no stopping rule. Given fewer iterations, the
  decays are compressed into them (what every run did before schedules existed).
* ``fast`` (the default): the paper's schedule, unchanged, cut at each method's
  ``FAST_ITERATIONS`` (or the iterations given): the learning rates and densification of the
  paper's run at the same iteration, and, for a method whose ``FAST_STOP_EVERY`` is set (the
  shape-guided one), a plateau rule (:class:`PlateauStop`) that ends the run sooner once the loss
  on every training view has stopped setting records. R2-Gaussian mode has none by default: its
  projections plateau long before its volume does (docs/schedules.md). A method's
  ``FAST_SETTINGS`` would change more of it (none does today: a TV patch every k-th iteration,
  ``tv_every``, was measured and saves 5-10 % of the thorax's time, docs/schedules.md).

:func:`resolve` turns a run's schedule and the settings given into the settings it runs with; the
config records both, so a run's ``config.json`` says what it did and a resumed run keeps it.
"""
from __future__ import annotations

import math

import torch

from clgs.errors import InputError
from clgs.fit.outputs import rendered_views

SCHEDULES = ("fast", "paper")
PAPER_ITERATIONS = 30_000  # R2-Gaussian's and the shape-guided paper's run length


def resolve(config_cls, iterations: int | None, settings: dict, n_views: int | None = None) -> dict:
    """The settings (JSON) of a new run of ``config_cls`` under its schedule (``settings["schedule"]``
    or the config's default): the class defaults, the schedule's, then ``settings`` and
    ``iterations`` as given (what is given always wins).

    ``paper``: 30 000 iterations unless given, the decays over the run; the plateau rule off.
    ``fast``: ``config_cls.FAST_ITERATIONS`` unless given; the decays as the paper's 30 000-iteration
    run has them (over more when more iterations are given), densification as the paper's; the
    plateau rule checking every ``FAST_STOP_EVERY`` iterations from half the run on (0: none), and
    the method's ``FAST_SETTINGS`` (settings measured to reach quality sooner, e.g. ``tv_every``),
    and on a scan of ``n_views`` >= the method's ``MANY_VIEWS`` its ``FAST_MANY_VIEWS`` (for
    R2-Gaussian mode: four views per step at twice the learning rates, and its own run length)."""
    base = config_cls().to_json()
    schedule = settings.get("schedule", base.get("schedule", "paper"))
    if schedule not in SCHEDULES:
        raise InputError(f"schedule must be one of {', '.join(SCHEDULES)}, got {schedule!r}")
    out = dict(base)
    if schedule == "paper":
        n = PAPER_ITERATIONS if iterations is None else int(iterations)
        out["stop_every"] = 0
    else:
        extra = dict(getattr(config_cls, "FAST_SETTINGS", {}))
        many = getattr(config_cls, "FAST_MANY_VIEWS", {})
        if many and n_views is not None and int(n_views) >= int(getattr(config_cls, "MANY_VIEWS", 0)):
            extra.update(many)
        fast_n = int(extra.pop("iterations", getattr(config_cls, "FAST_ITERATIONS", PAPER_ITERATIONS)))
        n = fast_n if iterations is None else int(iterations)
        out["schedule_iterations"] = max(n, PAPER_ITERATIONS)
        out["stop_every"] = int(getattr(config_cls, "FAST_STOP_EVERY", 0))
        out.update(extra)
    out.update(settings)
    out["iterations"] = n
    out["schedule"] = schedule
    return out


def views_loss(trainer) -> float:
    """Mean absolute difference between the model's projections and the measured ones over every
    training view (training units, no gradients): the training signal the plateau rule reads. Only
    the trainer's projections enter; a scan's truth never does."""
    total, count = 0.0, 0
    for pred, target in rendered_views(trainer):
        total += float((pred - target).abs().sum())
        count += pred.numel()
    return total / max(count, 1)


class PlateauStop:
    """Ends a run when its projections have stopped improving.

    Every ``every`` iterations (from ``after`` on) the loss on every training view is measured
    (:func:`views_loss`). The run has converged when ``patience`` checks in a row brought no loss
    lower than the best so far by more than ``tolerance`` of it (the best, not the last check: a
    loss that wanders up and down while the learning rates are high is not a plateau until it
    stops setting records). The trainer then stops after
    that iteration as a finished run (``trainer.converged`` says when and why), writes its
    checkpoint and outputs; resuming it does nothing more. Deterministic (no clock, no truth), and
    checkpointed with the run, so a resumed run stops where the uninterrupted one does.
    """

    request_stop_rule = True  # what the trainer looks for to say its estimate is an upper bound

    def __init__(self, every: int, tolerance: float, patience: int = 2, after: int = 0):
        if every < 0 or patience < 1 or not (math.isfinite(tolerance) and tolerance >= 0):
            raise InputError(f"plateau rule: every >= 0, patience >= 1 and tolerance >= 0 needed, got {every}, "
                             f"{patience}, {tolerance}")
        self.every, self.tolerance, self.patience, self.after = int(every), float(tolerance), int(patience), int(after)
        self.history: list = []  # (iteration, loss) of each check
        self.flat = 0  # checks in a row below the tolerance

    def on_iteration(self, trainer) -> None:
        it = trainer.iteration
        if self.every <= 0 or it < self.after or it % self.every or it >= trainer.iterations:
            return
        loss = views_loss(trainer)
        if self.history:
            best = min(v for _, v in self.history)
            self.flat = 0 if loss < best * (1 - self.tolerance) else self.flat + 1
        self.history.append((it, loss))
        if self.flat >= self.patience:
            trainer.request_stop({
                "iteration": it, "views_l1": loss,
                "reason": (f"the loss on every training view has not gone {100 * self.tolerance:g} % below its best "
                           f"in the last {self.patience} checks ({self.every} iterations apart)")})

    def state_dict(self) -> dict:
        return {"history": [list(h) for h in self.history], "flat": self.flat}

    def load_state_dict(self, state: dict) -> None:
        self.history = [(int(i), float(v)) for i, v in state.get("history", [])]
        self.flat = int(state.get("flat", 0))


def bin_projections(projections: torch.Tensor, factor: int) -> torch.Tensor:
    """(n, V, U) projections averaged over ``factor`` x ``factor`` pixel blocks: what the binned
    detector (:meth:`clgs.geometry.Geometry.binned`) measures of the same line integrals."""
    n, nv, nu = projections.shape
    f = int(factor)
    return projections.reshape(n, nv // f, f, nu // f, f).mean((2, 4)).contiguous()


class CoarseToFine:
    """Trainer hook: the first ``until`` iterations render and compare on a detector binned by
    ``factor`` (``factor``^2 fewer pixels: a cheaper projection while the scene is still coarse),
    the rest at full resolution. It swaps the trainer's geometry and projections; the run's data
    identity (checkpoints) stays the full scan's. Its state is the iteration count alone, so a
    resumed run trains at the resolution the uninterrupted one had."""

    def __init__(self, trainer, factor: int, until: int):
        self.factor, self.until = int(factor), int(until)
        _ = trainer.data_id  # of the full data, before any swap
        self.full = (trainer.geometry, trainer.projections)
        self.coarse = (trainer.geometry.binned(self.factor), bin_projections(trainer.projections, self.factor))
        self.on_fit(trainer)

    def on_fit(self, trainer) -> None:
        geometry, projections = self.coarse if trainer.iteration < self.until else self.full
        trainer.geometry, trainer.projections = geometry, projections

    def on_iteration(self, trainer) -> None:
        if trainer.iteration == self.until:
            self.on_fit(trainer)


def coarse_hook(trainer, cfg) -> CoarseToFine | None:
    """Coarse-to-fine rendering when the settings ask for it (``coarse_until`` > 0: that fraction
    of the run on a detector binned by ``coarse_factor``) and the detector's sides allow the
    binning; None otherwise."""
    frac = float(getattr(cfg, "coarse_until", 0.0) or 0.0)
    f = int(getattr(cfg, "coarse_factor", 2))
    nv, nu = trainer.geometry.nDetector
    if frac <= 0 or f < 2 or nv % f or nu % f:
        return None
    return CoarseToFine(trainer, f, int(round(frac * cfg.iterations)))


def plateau_hook(cfg) -> PlateauStop | None:
    """The plateau rule a run's settings ask for (None when ``stop_every`` is 0): checks every
    ``stop_every`` iterations from half the run on (or from the end of densification, when that
    comes sooner: new Gaussians make the loss jump)."""
    every = int(getattr(cfg, "stop_every", 0) or 0)
    if every <= 0:
        return None
    after = max(min(int(getattr(cfg, "densify_until", 0)), cfg.iterations // 2), every)
    return PlateauStop(every, float(cfg.stop_tolerance), int(cfg.stop_patience), after=after)
