"""The expected run time of a Gaussian fit, from the run's own first iterations.

Why here and why so: an R2-Gaussian run is thousands of iterations (the paper's schedule 30 000: hours on a CPU); a user
should know that in the first seconds, not after. The trainer times its first iterations (the very
iterations of the run: nothing is run twice and nothing is changed, the clock is only read), and
:class:`WarmUp` extrapolates: the time already spent since the run began (loading, FDK,
initialisation, registrations: the setup phases), the remaining iterations at the warm-up's mean
time per iteration, the evaluations still due at the time the first one took, and one evaluation's
time more for the volume and the files at the end. The first iteration is not timed (it builds the
OpenCL programs). Rough by nature: densification adds Gaussians later on, so a run that grows them
takes longer; the bar's ``left`` follows the run as it goes.

:func:`run_clock` marks where a run begins (a method's entry); the estimate is shown through
:func:`clgs.progress.note` when the whole run is expected to take more than :data:`MIN_SECONDS`.
"""
from __future__ import annotations

import contextlib
import contextvars
import time
from dataclasses import dataclass

MIN_SECONDS = 60.0  # runs expected to take longer get the estimate printed
SKIP = 1  # first iterations not timed: the first builds the kernels
WARMUP = 5  # iterations timed after those
HINT = "fewer iterations shorten it: --set iterations=N (Python: iterations=N)"

_RUN_START = contextvars.ContextVar("clgs_run_start", default=None)


@contextlib.contextmanager
def run_clock(clock=time.perf_counter):
    """Within: the run began now (its setup phases count in the estimate); an enclosing one wins."""
    if _RUN_START.get() is not None:
        yield
        return
    token = _RUN_START.set(clock())
    try:
        yield
    finally:
        _RUN_START.reset(token)


def run_started():
    """The clock reading at the start of the enclosing run (:func:`run_clock`), or None."""
    return _RUN_START.get()


@dataclass(frozen=True)
class Estimate:
    """A run's expected time, in parts (seconds)."""

    done_s: float  # spent when the estimate was made (setup and the warm-up)
    iterations: int  # still to run
    per_iteration_s: float
    evaluations: int  # still due
    per_evaluation_s: float
    after_s: float  # the volume and the files at the end

    @property
    def total_s(self) -> float:
        return (self.done_s + self.iterations * self.per_iteration_s + self.evaluations * self.per_evaluation_s
                + self.after_s)

    def message(self, hint: str = HINT) -> str:
        from clgs.progress import format_seconds as f

        per_1000 = 1000 * self.per_iteration_s
        parts = [f"{f(self.done_s)} so far", f"{self.iterations} iterations more at {f(self.per_iteration_s)}"]
        if self.evaluations:
            parts.append(f"{self.evaluations} evaluations at {f(self.per_evaluation_s)}")
        return (f"expected run time: about {f(self.total_s)} ({'; '.join(parts)}); {hint}, "
                f"each 1000 iterations take about {f(per_1000)}")


class WarmUp:
    """Times a trainer's first iterations (after ``skip``) and makes an :class:`Estimate` once
    ``warmup`` are timed. ``clock``: read for the time since ``run_start`` (default: the enclosing
    :func:`run_clock`, else the first reading), injected by tests."""

    def __init__(self, start_iteration: int, total_iterations: int, log_due=None, clock=time.perf_counter,
                 skip: int = SKIP, warmup: int = WARMUP, run_start=None):
        self.start = int(start_iteration)
        self.total = int(total_iterations)
        self.log_due = log_due or (lambda it: False)
        self.clock = clock
        self.skip, self.warmup = int(skip), int(warmup)
        self.run_start = run_start if run_start is not None else run_started()
        if self.run_start is None:
            self.run_start = clock()
        self.steps: list = []
        self.evaluations: list = []
        self.estimate: Estimate | None = None

    @property
    def wanted(self) -> bool:
        """Whether the run is long enough to time a warm-up and still have iterations left."""
        return self.estimate is None and self.total - self.start > self.skip + self.warmup

    def evaluation(self, seconds: float) -> None:
        self.evaluations.append(float(seconds))

    def step(self, iteration: int, seconds: float) -> Estimate | None:
        """The step that ended at ``iteration`` took ``seconds``; returns the estimate when this
        step completes the warm-up (once), else None."""
        if not self.wanted or iteration - self.start <= self.skip:
            return None
        self.steps.append(float(seconds))
        if len(self.steps) < self.warmup:
            return None
        per_it = sum(self.steps) / len(self.steps)
        per_eval = (sum(self.evaluations) / len(self.evaluations)) if self.evaluations else 0.0
        due = 0
        if self.evaluations:  # a run that evaluates (a resumed one may not have timed one yet: then 0)
            due = sum(1 for it in range(iteration + 1, self.total + 1) if self.log_due(it))
            due += 0 if self.log_due(self.total) else 1  # the closing row
        self.estimate = Estimate(done_s=max(self.clock() - self.run_start, 0.0), iterations=self.total - iteration,
                                 per_iteration_s=per_it, evaluations=due, per_evaluation_s=per_eval,
                                 after_s=per_eval)
        return self.estimate


def worth_telling(estimate: Estimate | None, min_seconds: float | None = None) -> bool:
    """Whether ``estimate`` is of a run long enough to print it (default: :data:`MIN_SECONDS`)."""
    return estimate is not None and estimate.total_s > (MIN_SECONDS if min_seconds is None else min_seconds)
