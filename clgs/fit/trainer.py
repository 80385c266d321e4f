"""A generic optimisation loop for Gaussian models of X-ray projections.

The loop knows nothing about a particular method. It takes

* ``sets``: named Gaussian sets. Each has ``name``, ``tensors()`` -> (means, scales, quats,
  densities) differentiable to its leaves, ``parameters()`` -> [(name, tensor, Schedule)],
  ``state_dict()`` / ``load_state_dict()`` and ``__len__``. The rendered scene is all sets together.
* ``losses``: :class:`LossTerm` (name, weight, fn(ctx) -> scalar). A term with weight 0 is never
  called, so it costs nothing (no projection, no voxelised patch). A term marked ``per_view``
  (the projection terms) is taken on each view of a step and averaged; the others (TV, priors)
  once per step.
* ``hooks``: objects with any of ``after_backward(trainer, ctx)`` (gradients are there, the
  step has not happened), ``on_iteration(trainer)`` (after the step; densification lives here),
  ``state_dict()`` / ``load_state_dict()`` (checkpointed with the run).

One iteration: set each parameter's learning rate from its schedule, take the next view of a
reshuffled stack (``views_per_step`` > 1: the next that many, each the context of the per-view
terms, all sharing the step's activations, TV patch and Adam update; R2-Gaussian takes one),
evaluate the loss terms on a lazily-built :class:`Context`, backward, Adam
(eps 1e-15) on the parameters whose learning rate is not 0, count the iteration, run hooks.
Every ``log_every`` iterations (and, with ``log_early``, at 10, 20, 50, 100, ... before the first)
the optional ``evaluate(trainer) -> dict`` adds a row to the log.
Every ``checkpoint_every`` iterations, on Ctrl-C and at the end, a checkpoint is written.
With ``progress``, a bar (named ``desc``) shows the log's figures and its training-time it/s
(:class:`clgs.fit.training_log.Progress`), and once the first iterations are timed the expected
run time is printed for a run longer than a minute (:mod:`clgs.fit.estimate`; ``estimate``
overrides; the clock is only read, so results do not change).

A stopping rule (a hook, e.g. :class:`clgs.fit.schedule.PlateauStop`) may end the run early as a
finished one (:meth:`Trainer.request_stop`): ``converged`` then says when and why, the checkpoint
records it, and a resumed run does nothing more.

Ctrl-C: the first SIGINT (main thread), or a SIGTERM (what ``timeout``, batch schedulers and
container stops send), asks the loop to stop at the end of the current iteration; the loop then
writes a checkpoint and returns with ``interrupted = True`` and ``stop_signal`` set to the signal
number (commands exit with 128 + that number: 130 for Ctrl-C, 143 for SIGTERM). A second
SIGINT, or a KeyboardInterrupt raised elsewhere (e.g. by a hook), stops at once; a checkpoint is
still written, and it is exact when the interruption came between iterations (hooks run there).

Determinism: views come from a NumPy Generator, everything random in the step (TV patches,
split positions) from the trainer's torch Generator; both are checkpointed, so a resumed run
continues bit for bit.
"""
from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from clgs.errors import InputError
from clgs.fit import checkpoint as ckpt
from clgs.fit.estimate import WarmUp
from clgs.fit.training_log import RATE, Progress, TrainingLog
from clgs.geometry import Grid
from clgs.ops.projector import project_packed
from clgs.ops.voxelizer import columns, cov_prec, grid_candidates, voxelize_precision
from clgs.reference import gaussians, voxelization
from clgs.reference.projection import project_patches

FINITE_CHECK_EVERY = 100  # iterations between checks that every parameter is finite


@dataclass
class LossTerm:
    """``weight x fn(ctx)`` in the total loss; ``weight == 0`` skips the term entirely, and ``fn``
    returning None skips it for that iteration."""

    name: str
    weight: float
    fn: Callable
    per_view: bool = False  # taken on each view of a multi-view step and averaged (projection terms)


class Backend:
    """Where projection and voxelisation run: ``"cl"`` (the OpenCL kernels) or ``"torch"`` (plain
    torch: the references' patch projector and windowed voxeliser, same maths, autograd for the
    gradients; for tests and the speed comparison)."""

    def __init__(self, name: str = "cl", mode: str = "affine"):
        if name not in ("cl", "torch"):
            raise InputError(f"backend must be 'cl' or 'torch', got {name!r}")
        if mode not in ("affine", "exact"):
            raise InputError(f"projector mode must be 'affine' or 'exact', got {mode!r}")
        self.name, self.mode = name, mode
        self._last = None
        if name == "cl":
            self._project, self._voxelize = self._cl_project, self._cl_voxelize
        else:
            self._voxelize = getattr(voxelization, "voxelize_windowed", voxelization.voxelize)
            self._project = self._torch_project

    # The kernels take packed covariances / precisions. One OpenCL kernel builds them for all N
    # Gaussians with their 3-sigma half-widths (and one kernel runs the closed-form backward):
    # element-wise torch on 50k Gaussians costs ~20x more on a CPU. During training the projection
    # asks for covariance, precision and half-widths at once, and the TV patch reuses them for the
    # same tensors (see _matrices): culling needs the half-widths of all N, the block only the
    # precisions of the few Gaussians that reach it, and their gradient joins the covariance's in
    # the one backward kernel.
    def _matrices(self, scales, quats):
        """(cov, prec, extent) for ``scales``/``quats``, from the last call when it was for the same
        tensors (same objects, unmodified, same grad mode), else computed now."""

        out = self._kept(scales, quats)
        if out is not None:
            return out
        out = cov_prec(scales, quats, cov=True, prec=True, extent=True)
        # kept for the voxelize call of the same step only when autograd records (training); the
        # trainer drops it after each step
        grad = torch.is_grad_enabled()
        self._last = (scales, quats, (scales._version, quats._version, grad), out) if grad else None
        return out

    def _kept(self, scales, quats):
        """The matrices kept by the last projection when they were built from these very tensors
        (unmodified since, same grad mode), else None."""
        last = self._last
        if (last is not None and last[0] is scales and last[1] is quats
                and last[2] == (scales._version, quats._version, torch.is_grad_enabled())):
            return last[3]
        return None

    def forget(self) -> None:
        """Drop the matrices kept from the last projection (and the graph they hold)."""
        self._last = None

    def _cl_project(self, means, scales, quats, densities, geometry, views, mode):
        if torch.is_grad_enabled() and (scales.requires_grad or quats.requires_grad):
            cov, prec, _ = self._matrices(scales, quats)
        else:  # evaluation: only what the projector reads
            cov, prec, _ = cov_prec(scales, quats, cov=(mode == "affine"), prec=(mode == "exact"))
        return project_packed(means, cov if mode == "affine" else prec, densities, geometry, views, mode=mode)

    def _cl_voxelize(self, means, scales, quats, densities, grid):
        kept = self._kept(scales, quats) if isinstance(grid, Grid) else None
        if kept is not None:
            return self.voxelize_shared(means, kept[1], densities, kept[2], grid)
        if isinstance(grid, Grid):
            # Only the Gaussians that can reach the grid (a 3-sigma box is at most 3 max(scale)
            # wide on any axis): for a 32^3 patch that is a few percent of them, and their
            # precisions are all that needs building.
            idx = grid_candidates(means, columns(scales.detach()).amax(0) * 3.003, grid)
            if idx is not None:
                means, scales, quats, densities = (t.index_select(0, idx) for t in (means, scales, quats, densities))
        _, prec, extent = cov_prec(scales, quats, cov=False, prec=True, extent=True)
        return voxelize_precision(means, prec, densities, extent, grid)

    @staticmethod
    def voxelize_shared(means, prec, densities, extent, grid):
        """The field on ``grid`` from every Gaussian's precision and half-widths (N, 6), (N, 3):
        culls by the exact 3-sigma boxes and hands the kernels only the rows that reach the grid
        (index_select keeps autograd exact: the others' gradients are 0)."""

        idx = grid_candidates(means, extent, grid)
        if idx is not None:
            means, prec, densities, extent = (t.index_select(0, idx) for t in (means, prec, densities, extent))
        return voxelize_precision(means, prec, densities, extent, grid, cull=False)

    def _torch_project(self, means, scales, quats, densities, geometry, views, mode):
        # the reference builds its Jacobians with torch.func, which returns NaN under no_grad here
        with torch.enable_grad():
            mats = (gaussians.covariance if mode == "affine" else gaussians.precision)(scales, quats)
            return torch.stack([project_patches(means, mats, densities, geometry, int(v), mode=mode) for v in views])

    def project(self, means, scales, quats, densities, geometry, views):
        return self._project(means, scales, quats, densities, geometry, list(views), mode=self.mode)

    def voxelize(self, means, scales, quats, densities, grid):
        return self._voxelize(means, scales, quats, densities, grid)


class Context:
    """What loss terms see during one iteration; costly pieces are built on first use."""

    def __init__(self, trainer: Trainer, view: int, views=None, _box=None):
        self.trainer = trainer
        self.view = view
        self.iteration = trainer.iteration
        self.generator = trainer.generator
        self.geometry = trainer.geometry
        # the scene's tensors, built on first use; one box for every view of a step, so a step's
        # activations are computed once (no reference back to the first context: no cycle)
        self._box = [None] if _box is None else _box
        self._render = None
        self._render_grad_box: list = []
        self._others = [Context(trainer, int(v), _box=self._box) for v in (views or [])[1:]]

    @property
    def group(self) -> list:
        """The contexts of every view of this step, this one first (one view: just this one)."""
        return [self, *self._others]

    @property
    def target(self) -> torch.Tensor:
        """The measured projection of this view (V, U), training units."""
        return self.trainer.projections[self.view]

    @property
    def tensors(self):
        """(means, scales, quats, densities) of all sets, concatenated."""
        if self._box[0] is None:
            self._box[0] = self.trainer.scene_tensors()
        return self._box[0]

    @property
    def render(self) -> torch.Tensor:
        """The model's projection of this view (V, U), training units."""
        if self._render is None:
            t = self.trainer
            means, *rest = self.tensors
            if means.requires_grad:  # an alias whose gradient is the projection's share alone
                means = means.view_as(means)
                # the hook appends to a plain list: a hook holding this context would tie the
                # context and the autograd graph into a cycle that Python's collector cannot see
                means.register_hook(self._render_grad_box.append)
            self._render = t.backend.project(means, *rest, t.geometry, [self.view])[0] * t.render_scale
        return self._render

    @property
    def render_means_grad(self):
        """dLoss/dmeans (all sets concatenated) through the projection only, after backward: what
        densification looks at (other terms, e.g. TV, also move the means but say nothing about
        under-fitted projections). None before backward or without a render."""
        return self._render_grad_box[-1] if self._render_grad_box else None

    def voxelize(self, grid, tensors=None) -> torch.Tensor:
        """The field of all sets (or of ``tensors``) on ``grid``, training units."""
        return self.trainer.backend.voxelize(*(tensors or self.tensors), grid)


def check_views_per_step(k: int, n_views: int) -> None:
    """A step's views (``views_per_step``) must be at least one and at most the training views."""
    if not 1 <= int(k) <= int(n_views):
        raise InputError(f"views_per_step must be between 1 and the {n_views} training views, got {k}")


def early_log_points(below: int) -> set:
    """1, 2 and 5 times the powers of ten from 10 up to ``below`` (excluded)."""
    out, decade = set(), 10
    while decade < below:
        out.update(m * decade for m in (1, 2, 5) if m * decade < below)
        decade *= 10
    return out


class Trainer:
    """Adam over named Gaussian sets, one view per iteration (or ``views_per_step``); see the
    module doc."""

    def __init__(self, sets, geometry, projections, losses, *, iterations: int, backend="cl",
                 render_scale: float = 1.0, seed: int = 0, hooks=(), evaluate=None, log_every: int = 500,
                 log_early: bool = False, checkpoint_every: int = 0, checkpoint_path=None, progress: bool = False,
                 views=None, config: dict | None = None, torch_threads: int | None = -1, desc: str = "train",
                 estimate: bool | None = None, views_per_step: int = 1):
        self.sets = list(sets)
        names = [s.name for s in self.sets]
        if len(set(names)) != len(names):
            raise InputError(f"Gaussian sets need distinct names, got {names}")
        self.geometry = geometry
        self.projections = torch.as_tensor(np.asarray(projections, dtype=np.float32))
        if self.projections.shape != (geometry.n_views, *geometry.nDetector):
            raise InputError(f"projections have shape {tuple(self.projections.shape)}, the geometry "
                             f"expects {(geometry.n_views, *geometry.nDetector)}")
        self.losses = list(losses)
        self.iterations = int(iterations)
        self.backend = backend if isinstance(backend, Backend) else Backend(backend)
        self.render_scale = float(render_scale)
        self.hooks = list(hooks)
        self.evaluate = evaluate
        self.log_every = int(log_every)
        self.log_early = bool(log_early)
        self.checkpoint_every = int(checkpoint_every)
        self.checkpoint_path = checkpoint_path
        self.progress_enabled = progress
        self.desc = desc  # the progress bar's name
        # print the expected run time after a timed warm-up (clgs.fit.estimate); None: with the bar
        self.estimate_enabled = progress if estimate is None else bool(estimate)
        self.expected = None  # the Estimate made, if any
        self.views = list(range(geometry.n_views)) if views is None else [int(v) for v in views]
        self.views_per_step = int(views_per_step)
        check_views_per_step(self.views_per_step, len(self.views))
        self.config = dict(config or {})
        self.seed = int(seed)
        # -1: automatic. With the OpenCL backend the torch side of an iteration is small element-wise
        # work on N Gaussians; torch's extra threads would only spin against the OpenCL runtime's
        # workers on the same cores, so one thread is used during fit (restored afterwards).
        if torch_threads == -1:
            torch_threads = 1 if self.backend.name == "cl" else None
        self.torch_threads = torch_threads
        self.generator = torch.Generator().manual_seed(self.seed)
        self.rng = np.random.default_rng(self.seed)
        self.iteration = 0
        self.view_stack: list = []
        self.log = TrainingLog()
        self.seconds = 0.0  # training time so far, over every run resumed from this one
        self.wall_offset = 0.0
        self.interrupted = False
        self.converged: dict | None = None  # set by a stopping rule (request_stop): the run is finished
        self._sums: dict = {}
        self._count = 0
        self._stop = False
        self._build_optimizer()

    # ------------------------------------------------------------------ model
    def _build_optimizer(self) -> None:
        groups = []
        self._schedules = []
        for s in self.sets:
            for name, tensor, schedule in s.parameters():
                groups.append({"params": [tensor], "lr": schedule(0), "name": f"{s.name}.{name}"})
                self._schedules.append(schedule)
        try:  # the fused CPU kernel is faster than foreach; same update
            self.optimizer = torch.optim.Adam(groups, eps=1e-15, fused=True)
        except (RuntimeError, TypeError, ValueError):
            self.optimizer = torch.optim.Adam(groups, eps=1e-15)

    def scene_tensors(self):
        parts = [s.tensors() for s in self.sets]
        if len(parts) == 1:
            return parts[0]
        return tuple(torch.cat([p[i] for p in parts], 0) for i in range(4))

    @property
    def n_gaussians(self) -> int:
        return sum(len(s) for s in self.sets)

    # ------------------------------------------------------------------ one step
    def next_views(self, k: int = 1) -> list:
        """The next ``k`` views of the reshuffled stack, each view once per pass. A step that runs
        past the end of a pass takes the rest of it and then, from the next pass, views it does not
        already hold (those are put last in the new pass), so a step's views are distinct; one view a
        step draws exactly as a plain pass-by-pass shuffle."""
        out: list = []
        while len(out) < k:
            if not self.view_stack:
                fresh = [self.views[i] for i in self.rng.permutation(len(self.views))]
                held = set(out)
                self.view_stack = [v for v in fresh if v in held] + [v for v in fresh if v not in held]
            out.append(self.view_stack.pop())
        return out

    def step(self) -> dict:
        """One iteration; returns the loss terms' values (floats)."""
        it = self.iteration
        for group, schedule in zip(self.optimizer.param_groups, self._schedules):
            group["lr"] = schedule(it)
        views = self.next_views(self.views_per_step)
        ctx = Context(self, views[0], views)
        total, values = None, {}
        for term in self.losses:
            if term.weight == 0:
                continue
            if term.per_view and len(ctx.group) > 1:
                parts = [term.fn(c) for c in ctx.group]
                v = None if any(p is None for p in parts) else sum(parts) / len(parts)
            else:
                v = term.fn(ctx)
            if v is None:  # the term sits this iteration out (e.g. a TV patch every k-th iteration)
                continue
            values[term.name] = v.detach()
            total = term.weight * v if total is None else total + term.weight * v
        self.optimizer.zero_grad(set_to_none=True)
        if total is not None:
            if not torch.isfinite(total):
                raise FloatingPointError(
                    f"the loss became {float(total.detach())} at iteration {it} "
                    f"(view{'s' if len(views) > 1 else ''} {', '.join(map(str, views))}); lower the learning "
                    "rates or check the projections for NaN/Inf")
            total.backward()
        for h in self.hooks:
            if hasattr(h, "after_backward"):
                h.after_backward(self, ctx)
        for group in self.optimizer.param_groups:
            if group["lr"] == 0:
                for p in group["params"]:
                    p.grad = None  # frozen: Adam's moments must not move either
        self.optimizer.step()
        if (it + 1) % FINITE_CHECK_EVERY == 0:
            self.check_finite()
        if hasattr(self.backend, "forget"):
            self.backend.forget()
        self.iteration += 1
        out = {k: float(v) for k, v in values.items()}
        out["loss"] = float(total.detach()) if total is not None else 0.0
        for k, v in out.items():  # running sums for the next log row (checkpointed)
            self._sums[k] = self._sums.get(k, 0.0) + v
        self._count += 1
        for h in self.hooks:
            if hasattr(h, "on_iteration"):
                h.on_iteration(self)
        return out

    def request_stop(self, converged: dict) -> None:
        """End the run after this iteration as a finished one (a stopping rule's call, e.g.
        :class:`clgs.fit.schedule.PlateauStop`): ``converged`` says when and why; the checkpoint,
        the closing log row and the outputs follow as at the last iteration, and resuming the run
        does nothing more."""
        self.converged = dict(converged)
        self._stop = True

    # ------------------------------------------------------------------ the loop
    def fit(self) -> Trainer:
        """Run to ``iterations`` (continuing from a resumed state); see the module doc for Ctrl-C."""
        self._stop = False
        self.interrupted = False
        t_wall = time.perf_counter() - self.wall_offset
        self.stop_signal = None
        old_handlers = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                old_handlers[sig] = signal.signal(sig, self._on_sigint)
        threads = torch.get_num_threads()
        if self.torch_threads:
            torch.set_num_threads(self.torch_threads)
        progress = Progress(self.iterations, self.iteration, self.progress_enabled, desc=self.desc)
        self._progress = progress
        warm = None
        if self.estimate_enabled:
            warm = WarmUp(self.iteration, self.iterations, self.log_due)
        start = (self.iteration, self.seconds)
        for h in self.hooks:  # e.g. the resolution a resumed run trains at
            if hasattr(h, "on_fit"):
                h.on_fit(self)
        try:
            try:
                if self.iteration == 0 and self.log_every > 0 and not self.log.rows:
                    self._log_row(t_wall, {}, warm)
                    progress.set_figures(self.log.headline())
                while self.iteration < self.iterations and not self._stop and self.converged is None:
                    t0 = time.perf_counter()
                    self.step()
                    took = time.perf_counter() - t0
                    self.seconds += took
                    if warm is not None and warm.step(self.iteration, took) is not None:
                        self._tell_estimate(warm.estimate)
                    progress.update(1, {**progress.figures, RATE: self._rate(start)})
                    if self.log_due(self.iteration):
                        self._log_row(t_wall, {}, warm)
                        progress.set_figures(self.log.headline())
                    if self.checkpoint_every > 0 and self.iteration % self.checkpoint_every == 0:
                        self.save_checkpoint(t_wall)
            except KeyboardInterrupt:
                self._stop = True
                self.stop_signal = self.stop_signal or signal.SIGINT
            finally:
                for sig, handler in old_handlers.items():
                    signal.signal(sig, handler)
                torch.set_num_threads(threads)
            if self._stop and self.converged is None:
                self.interrupted = True
            elif self.converged is not None and self.progress_enabled:
                from clgs.progress import note

                note(f"converged at iteration {self.converged['iteration']} of {self.iterations}: "
                     f"{self.converged['reason']}; stopped (--set stop_every=0 runs every iteration)",
                     bar=getattr(progress, "bar", None))
            self.check_finite()
            # checkpoint first: the closing row below is off the logging schedule, and a resumed run
            # must log exactly what an uninterrupted one does
            self.save_checkpoint(t_wall)
            logged = bool(self.log.rows) and self.log.rows[-1]["iteration"] == self.iteration
            if self.log_every > 0 and self._count > 0 and not logged:
                self._log_row(t_wall, {})
            # the bar ends on the summary's figures: the last row's and its it/s
            progress.finish(self.log.headline() if self.log.rows else {RATE: self._rate(start)})
        finally:
            progress.close()
        return self

    def _rate(self, start) -> float | None:
        """Iterations per second of training: the log's (from its first row), or since ``start``
        (iteration, seconds) for a run that logs nothing."""
        if self.log.rows:
            return self.log.rate(self.iteration, self.seconds)
        its, secs = self.iteration - start[0], self.seconds - start[1]
        return its / secs if its > 0 and secs > 0 else None

    def _tell_estimate(self, estimate) -> None:
        from clgs.fit.estimate import worth_telling
        from clgs.progress import note

        self.expected = estimate
        if worth_telling(estimate):
            text = estimate.message()
            if any(hasattr(h, "request_stop_rule") for h in self.hooks):
                text += "; at most: the run stops sooner once its projections stop improving"
            note(text, bar=getattr(self._progress, "bar", None))

    def log_due(self, iteration: int) -> bool:
        """Whether ``iteration`` gets a log row: every ``log_every``, and with ``log_early`` also at
        10, 20, 50, 100, 200, 500, ... below the first ``log_every``, where the error falls fastest
        (so the time to each quality level is told apart; a few evaluations more per run)."""
        if self.log_every <= 0:
            return False
        if iteration % self.log_every == 0:
            return True
        return self.log_early and iteration < self.log_every and iteration in early_log_points(self.log_every)

    def _on_sigint(self, signum, frame):
        if self._stop:
            raise KeyboardInterrupt
        self._stop = True
        self.stop_signal = int(signum)
        what = "interrupt" if signum == signal.SIGINT else f"signal {signal.Signals(signum).name}"
        saving = " and saving a checkpoint" if self.checkpoint_path is not None else ""
        msg = f"{what}: stopping after this iteration{saving} (Ctrl-C again to abort at once)"
        if getattr(self, "_progress", None) is not None and self._progress.bar is not None:
            self._progress.write(msg)

    def _log_row(self, t_wall: float, values: dict, warm=None) -> None:
        t0 = time.perf_counter()
        row = {"iteration": self.iteration, "seconds": round(self.seconds, 4),
               "wall": round(time.perf_counter() - t_wall, 4), "n_gaussians": self.n_gaussians}
        if self._count:
            row.update({k: v / self._count for k, v in self._sums.items()})
        if self.evaluate is not None:
            with torch.no_grad():
                row.update(self.evaluate(self))
            if warm is not None:
                warm.evaluation(time.perf_counter() - t0)
        self.log.add(row)
        self._sums, self._count = {}, 0
        if self.checkpoint_path is not None:  # the run folder's log.csv follows a long run live
            self.log.write_csv(Path(self.checkpoint_path).parent / "log.csv")

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self, t_wall: float | None = None) -> dict:
        wall = (time.perf_counter() - t_wall) if t_wall is not None else self.wall_offset
        return {
            "iteration": self.iteration,
            "iterations": self.iterations,
            "sets": {s.name: s.state_dict() for s in self.sets},
            "optimizer": self.optimizer.state_dict(),
            "hooks": [h.state_dict() if hasattr(h, "state_dict") else {} for h in self.hooks],
            "torch_rng": self.generator.get_state(),
            "numpy_rng": ckpt.dumps(self.rng.bit_generator.state),
            "view_stack": list(self.view_stack),
            "log": ckpt.dumps(self.log.rows),
            "sums": ckpt.dumps(self._sums),
            "count": self._count,
            "seconds": self.seconds,
            "wall": wall,
            "seed": self.seed,
            "config": ckpt.dumps(self.config),
            "data": self.data_id,
            "converged": ckpt.dumps(self.converged),
        }

    @property
    def data_id(self) -> str:
        """A digest of the projections (as trained on) and the views' geometry: a checkpoint made on
        other data is refused on resume."""
        if getattr(self, "_data_id", None) is None:
            import hashlib

            h = hashlib.sha256(np.ascontiguousarray(self.projections.numpy()).tobytes())
            h.update(np.ascontiguousarray(self.geometry.view_vectors(scene=True), np.float64).tobytes())
            self._data_id = h.hexdigest()
        return self._data_id

    def load_state_dict(self, state: dict) -> None:
        missing = [k for k in ("iteration", "sets", "optimizer", "hooks", "torch_rng", "numpy_rng", "view_stack",
                               "log", "sums", "count", "seconds", "wall") if k not in state]
        if missing:
            raise ckpt.CheckpointError(f"checkpoint lacks {', '.join(missing)}: not a complete clgs checkpoint")
        if state.get("data") is not None and state["data"] != self.data_id:
            raise ckpt.CheckpointError("checkpoint was made on other projections or another scan geometry: resume "
                                       "it on the scan it was started on, or start a new run")
        names = sorted(s.name for s in self.sets)
        if sorted(state["sets"]) != names:
            raise ckpt.CheckpointError(f"checkpoint holds sets {sorted(state['sets'])}, this run has {names}")
        for s in self.sets:
            s.load_state_dict(state["sets"][s.name])
        self._build_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        for h, hs in zip(self.hooks, state["hooks"]):
            if hasattr(h, "load_state_dict"):
                h.load_state_dict(hs)
        self.generator.set_state(state["torch_rng"])
        self.rng.bit_generator.state = ckpt.loads(state["numpy_rng"])
        self.view_stack = [int(v) for v in state["view_stack"]]
        self.log = TrainingLog(ckpt.loads(state["log"]))
        self._sums = ckpt.loads(state["sums"])
        self._count = int(state["count"])
        self.iteration = int(state["iteration"])
        if self.iteration < 0:
            raise ckpt.CheckpointError(f"checkpoint iteration must be >= 0, got {self.iteration}")
        bad = self._bad_parameters()
        if bad:
            raise ckpt.CheckpointError(f"checkpoint parameters {', '.join(bad)} hold NaN or Inf: it cannot be "
                                       "resumed; start the run again")
        self.seconds = float(state["seconds"])
        self.wall_offset = float(state["wall"])
        self.converged = ckpt.loads(state["converged"]) if state.get("converged") is not None else None

    def save_checkpoint(self, t_wall: float | None = None):
        if self.checkpoint_path is None:
            return None
        self.check_finite()  # a checkpoint is never overwritten by a broken state
        return ckpt.save(self.checkpoint_path, self.state_dict(t_wall))

    def _bad_parameters(self) -> list:
        with torch.no_grad():
            return [f"{s.name}.{name}" for s in self.sets for name, t, _ in s.parameters()
                    if t.numel() and not bool(torch.isfinite(t).all())]

    def check_finite(self) -> None:
        """Raise FloatingPointError when a parameter holds NaN or Inf. The kernels skip such
        Gaussians, so the loss can stay finite while the model is broken; checked every
        ``FINITE_CHECK_EVERY`` iterations, before each checkpoint and at the end of a run, so the
        last checkpoint on disk always holds finite parameters."""
        bad = self._bad_parameters()
        if bad:
            kept = ""
            if self.checkpoint_path is not None and Path(self.checkpoint_path).is_file():
                kept = f"; the last checkpoint ({self.checkpoint_path}) is kept"
            raise FloatingPointError(
                f"parameters {', '.join(bad)} became NaN or Inf by iteration {self.iteration}{kept}: lower the "
                "learning rates or check the projections and settings")

    def resume(self, path=None) -> Trainer:
        """Load the checkpoint at ``path`` (default: ``checkpoint_path``)."""
        self.load_state_dict(ckpt.load(path or self.checkpoint_path))
        return self
