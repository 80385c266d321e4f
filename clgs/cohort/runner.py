"""Run a list of independent tasks here (one after another) or on Dask, and gather outcomes.

A task is a plain module-level function with small picklable arguments (paths, dicts, seeds):
whatever it needs in bulk (scans, the anatomy's model) it reads itself from a path every worker
sees. It writes its own outputs (atomically) before it returns, so a finished task is never
lost, and returns a small result (a table row).

An exception inside a task becomes that task's :class:`Outcome` with its error; the other tasks go
on. A worker process that dies (``kill -9``, out of memory) costs only the task it was running:
the scheduler runs it again on another worker (up to
:data:`clgs.cohort.cluster.ALLOWED_FAILURES` deaths per task).

``workers`` None or 0 and no ``scheduler``: every task runs in this process, in order, exactly as
a plain loop would (no Dask import).
"""
from __future__ import annotations

import contextlib
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


class Stopped(KeyboardInterrupt):
    """A list of tasks stopped by SIGINT (Ctrl-C) or SIGTERM: ``signum`` says which."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)
        self.running = []  # keys of the tasks it cut (in this process)


class StopSignals:
    """SIGINT and SIGTERM while a list of tasks runs (installed by :func:`stop_signals`).

    The first signal asks the list to stop: no task starts after it. A training run in this
    process takes the signal itself (its trainer's handler stands in for this one while it trains):
    it saves its checkpoint and returns as interrupted. Anything else that runs (FDK, SART, a run
    still loading; or this process waiting for Dask workers) cannot save where it is and is cut at
    once (:class:`Stopped` is raised there). A second signal cuts whatever runs."""

    def __init__(self):
        self.signum = None
        self.cut_now = False  # set while a task that does not stop by itself runs here, or while waiting

    def __call__(self, signum, frame):
        first = self.signum is None
        self.signum = self.signum or int(signum)
        if self.cut_now or not first:
            raise Stopped(self.signum)

    def request(self, signum) -> None:
        """A task stopped by a signal it took itself: stop the list too."""
        self.signum = self.signum or int(signum)


@contextlib.contextmanager
def stop_signals():
    """A :class:`StopSignals` installed for SIGINT and SIGTERM in the block (main thread only;
    elsewhere it is never triggered), the previous handlers restored after."""
    import signal
    import threading

    stop = StopSignals()
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, stop)
    try:
        yield stop
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


@dataclass
class Task:
    """One run: ``fn(*args, **kwargs)``; ``key`` names it (unique within a list)."""

    key: str
    fn: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)


@dataclass
class Outcome:
    """What became of a task: its ``result``, or its ``error`` (a one-line message) and traceback."""

    key: str
    result: Any = None
    error: str | None = None
    traceback: str | None = None
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.error is None


@contextlib.contextmanager
def torch_single_thread():
    """torch at one thread for the block (then as it was). Some of its CPU operations (matrix
    products, reductions) split the work by the thread count and so round differently with 1 or 2
    threads; the training loop already runs at one thread, this holds the rest of a run to the same,
    so that a result does not depend on the share of cores of the process it ran in."""
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a dependency
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def call_task(fn, args, kwargs) -> dict:
    """Run one task where it is (this process or a worker), torch at one thread (see
    :func:`torch_single_thread`); an exception is returned, not raised, so that it is reported
    rather than retried (a bad scan fails the same way everywhere)."""
    t0 = time.perf_counter()
    try:
        with torch_single_thread():
            result = fn(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 - any failure of one run is that run's outcome
        return {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(),
                "seconds": time.perf_counter() - t0}
    return {"result": result, "seconds": time.perf_counter() - t0}


def _outcome(key, raw: dict) -> Outcome:
    return Outcome(key, raw.get("result"), raw.get("error"), raw.get("traceback"), float(raw.get("seconds", 0.0)))


def _check_keys(tasks) -> None:
    from clgs.errors import InputError

    keys = [t.key for t in tasks]
    if len(set(keys)) != len(keys):
        dup = sorted({k for k in keys if keys.count(k) > 1})
        raise InputError(f"task keys must be unique, these repeat: {dup}")


def run_tasks(tasks, workers: int | None = None, scheduler: str | None = None,
              on_outcome: Callable[[Outcome], None] | None = None, desc: str = "runs", progress: bool = True,
              echo=print, stop: StopSignals | None = None) -> list:
    """Run ``tasks`` (:class:`Task`) and return their :class:`Outcome` in the tasks' order (of those
    that ran: with ``stop``, a signal ends the list early, see :class:`StopSignals`).

    workers: None or 0 runs them here, one after another; N >= 1 starts a local cluster of N
    worker processes. scheduler: the address (tcp://HOST:PORT) of a running Dask scheduler.
    on_outcome(outcome) is called here as each task ends (in the order they end), e.g. to rewrite
    a summary. A progress bar counts the tasks as they end."""
    from clgs.cohort.cluster import check_choice, distributed_wanted
    from clgs.progress import progress_bar

    tasks = list(tasks)
    _check_keys(tasks)
    check_choice(workers, scheduler)
    outcomes = {}
    if not tasks:
        return []
    bar = progress_bar(total=len(tasks), desc=desc, unit="run", disable=not progress)
    try:
        if not distributed_wanted(workers, scheduler):
            for task in tasks:
                if stop is not None and stop.signum is not None:
                    break
                try:
                    with _cut_now(stop, True):
                        raw = call_task(task.fn, task.args, task.kwargs)
                except Stopped as exc:
                    exc.running = [task.key]
                    raise
                out = _outcome(task.key, raw)
                outcomes[task.key] = out
                bar.update(1)
                if on_outcome is not None:
                    on_outcome(out)
        else:
            _run_on_dask(tasks, workers, scheduler, outcomes, bar, on_outcome, echo, stop)
    finally:
        bar.close()
    return [outcomes[t.key] for t in tasks if t.key in outcomes]


@contextlib.contextmanager
def _cut_now(stop, value: bool):
    if stop is None:
        yield
        return
    before, stop.cut_now = stop.cut_now, value
    try:
        yield
    finally:
        stop.cut_now = before


def _run_on_dask(tasks, workers, scheduler, outcomes, bar, on_outcome, echo, stop=None) -> None:
    from distributed import as_completed

    from clgs.cohort.cluster import open_client

    with open_client(workers, scheduler, echo=echo) as (client, resources):
        futures, keys = [], {}
        for task in tasks:
            # a fresh key per submission: a re-run of the same list is new work, not a cached result
            fut = client.submit(call_task, task.fn, task.args, task.kwargs, pure=False, resources=resources,
                                key=f"clgs-{task.key}-{uuid.uuid4().hex[:8]}")
            futures.append(fut)
            keys[fut.key] = task.key
        if stop is not None and stop.signum is not None:
            raise Stopped(stop.signum)
        waiting = as_completed(futures)
        while True:
            with _cut_now(stop, True):  # a signal while waiting for workers stops the list at once
                fut = next(waiting, None)
            if fut is None:
                break
            key = keys[fut.key]
            try:
                raw = fut.result()
            except Exception as exc:  # noqa: BLE001 - the task's worker died too often (KilledWorker), ...
                raw = {"error": _worker_error(exc, workers), "traceback": traceback.format_exc()}
            out = _outcome(key, raw)
            outcomes[key] = out
            bar.update(1)
            if on_outcome is not None:
                on_outcome(out)
            if stop is not None and stop.signum is not None:
                raise Stopped(stop.signum)


def _worker_error(exc: BaseException, workers) -> str:
    """A task's error on Dask as one line; a worker process that kept dying gets its likely cause."""
    if type(exc).__name__ != "KilledWorker":
        return f"{type(exc).__name__}: {exc}"
    from clgs.cohort.cluster import ALLOWED_FAILURES, memory_advice

    return (f"KilledWorker: the worker process running it died {ALLOWED_FAILURES + 1} times (killed from outside, "
            f"or for lack of memory); {memory_advice(workers)}")
