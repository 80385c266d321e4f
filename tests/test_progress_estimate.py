"""The expected run time's arithmetic, with an injected clock (no test depends on wall time)."""
import pytest

from clgs.fit.estimate import Estimate, WarmUp, run_clock, run_started, worth_telling


class _Clock:
    def __init__(self, t=0.0):
        self.t = t

    def __call__(self):
        return self.t


def _warm(clock, total=1000, start=0):
    return WarmUp(start, total, log_due=lambda it: it % 100 == 0, clock=clock, skip=1, warmup=5, run_start=0.0)


def test_the_warm_up_extrapolates_iterations_evaluations_and_the_setup_done():
    clock = _Clock()
    w = _warm(clock)
    w.evaluation(2.0)  # the row at iteration 0
    assert w.step(1, 5.0) is None  # the first iteration (kernel builds) is not timed
    for it in range(2, 6):
        assert w.step(it, 0.5) is None
    clock.t = 30.0  # setup and warm-up so far
    e = w.step(6, 0.5)
    assert e == Estimate(done_s=30.0, iterations=994, per_iteration_s=0.5, evaluations=10, per_evaluation_s=2.0,
                         after_s=2.0)
    assert e.total_s == pytest.approx(30 + 497 + 20 + 2)
    assert w.step(7, 0.5) is None and w.estimate is e  # made once
    text = e.message()
    assert text.startswith("expected run time: about 9 min 9 s (30 s so far; 994 iterations more at 0.50 s; "
                           "10 evaluations at 2.0 s)")
    assert "--set iterations=N" in text and "each 1000 iterations take about 8 min 20 s" in text


def test_a_closing_row_off_the_schedule_counts_and_a_resumed_run_starts_where_it_was():
    clock = _Clock(10.0)
    w = WarmUp(500, 1050, log_due=lambda it: it % 100 == 0, clock=clock, skip=1, warmup=2, run_start=4.0)
    w.evaluation(1.0)
    w.step(501, 9.0)
    w.step(502, 0.2)
    e = w.step(503, 0.4)
    assert (e.iterations, e.evaluations, e.done_s) == (547, 6, 6.0)  # 600..1000 and the closing row at 1050
    assert e.per_iteration_s == pytest.approx(0.3)


def test_runs_too_short_for_a_warm_up_get_no_estimate():
    w = _warm(_Clock(), total=6)
    assert not w.wanted
    assert all(w.step(it, 1.0) is None for it in range(1, 7))


def test_only_runs_longer_than_a_minute_are_told():
    short = Estimate(done_s=10, iterations=100, per_iteration_s=0.3, evaluations=1, per_evaluation_s=1, after_s=1)
    long = Estimate(done_s=10, iterations=1000, per_iteration_s=0.3, evaluations=1, per_evaluation_s=1, after_s=1)
    assert not worth_telling(short) and worth_telling(long) and not worth_telling(None)
    assert worth_telling(short, min_seconds=5)


def test_the_run_clock_marks_the_outer_start():
    clock = _Clock(3.0)
    assert run_started() is None
    with run_clock(clock):
        clock.t = 8.0
        with run_clock(clock):  # a method inside another run: the outer start counts
            assert run_started() == 3.0
            w = WarmUp(0, 100, clock=clock)
            assert w.run_start == 3.0
    assert run_started() is None
