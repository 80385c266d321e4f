"""Starting or joining a Dask cluster, with the cores shared between its worker processes.

Each worker process builds its own OpenCL context on its first task (nothing OpenCL is ever
pickled). Its share of the cores is set before that happens, through environment variables that
PoCL reads when its platform starts (``POCL_MAX_PTHREAD_COUNT``, ``POCL_CPU_MAX_CU_NUM``), those of
Intel's CPU runtime (``DPCPP_CPU_NUM_CUS``, ``CL_CONFIG_CPU_TBB_NUM_WORKERS``) and the usual thread
counts of numpy's and torch's libraries; PoCL's thread pinning is turned off, since
workers pinning their threads to the same first cores would share them.

A local cluster's workers each advertise one ``clgs-run`` resource and every task asks for it, so a
worker runs one task at a time with all of its threads. On a running cluster the same happens
where its workers were started with ``--resources clgs-run=1``; elsewhere a worker may run as many
tasks at once as it has threads.
"""
from __future__ import annotations

import contextlib
import logging
import os

from clgs.errors import InputError
from clgs.limits import available_memory, total_memory  # noqa: F401  (read here; tests patch them here)

RESOURCE = "clgs-run"
# worker deaths (a killed process, lost memory) a task may see before it counts as failed
ALLOWED_FAILURES = 3


def thread_env(threads: int) -> dict:
    """Environment variables that hold a process's compute libraries to ``threads`` threads."""
    n = str(max(1, int(threads)))
    return {"POCL_MAX_PTHREAD_COUNT": n, "POCL_CPU_MAX_CU_NUM": n, "POCL_AFFINITY": "0", "OMP_NUM_THREADS": n,
            "MKL_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n,
            # Intel's CPU OpenCL runtime (oneTBB underneath)
            "DPCPP_CPU_NUM_CUS": n, "CL_CONFIG_CPU_TBB_NUM_WORKERS": n}


def cores() -> int:
    """Cores this process may use (its affinity mask)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def check_choice(workers, scheduler) -> None:
    """``workers`` and ``scheduler`` are two ways to pick a cluster: at most one, and sensible
    (:func:`check_form`), and no more local workers than this machine holds (:func:`check_workers`)."""
    check_form(workers, scheduler)
    if workers and not scheduler:
        check_workers(workers)


def check_form(workers, scheduler) -> None:
    """At most one of ``workers`` and ``scheduler``, each well formed (a usage error on the command line)."""
    if workers is not None and scheduler:
        raise InputError("give --workers N (a local cluster) or --scheduler ADDRESS (a running one), not both")
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 0):
        raise InputError(f"workers must be a whole number >= 0 (0: run here, one after another), got {workers!r}")
    if scheduler is not None and (not isinstance(scheduler, str) or "://" not in scheduler):
        raise InputError(f"scheduler {scheduler!r} is not an address: give it as tcp://HOST:PORT")


# memory a worker process takes before its first run (Python, NumPy, torch, PyOpenCL, Dask: about
# 0.4 GiB measured) plus a small run's working set: the floor under which workers start dying
WORKER_MIB = 600
# more worker processes than this many per core only share the cores (each has at least one thread)
WORKERS_PER_CORE = 2




def suggested_workers() -> int:
    """The most local workers this machine runs well: one per core, fewer where memory is short."""
    free = available_memory()
    by_memory = cores() if free is None else max(1, int(free // (WORKER_MIB * 2**20)))
    return max(1, min(cores(), by_memory))


def memory_advice(workers) -> str:
    """What each local worker had against the machine's memory, and a worker count to try."""
    total, free = total_memory(), available_memory()
    if workers and total:
        share = f"{int(workers)} workers shared {total / 2**30:.1f} GiB, {total / int(workers) / 2**30:.2f} GiB each"
    else:
        share = "the workers' memory is set where they were started"
    now = f" ({free / 2**30:.1f} GiB available now)" if free is not None else ""
    return (f"{share}{now}; a run needs its scan, volume and Gaussians in memory: run again with fewer workers "
            f"(--workers {max(1, min(suggested_workers(), int(workers or 2) // 2 or 1))}) or on a machine with more "
            "memory")


def check_workers(workers) -> None:
    """Refuse, before any work, a local cluster far beyond this machine's cores or memory."""
    if not workers:
        return
    n, c, free = int(workers), cores(), available_memory()
    need = n * WORKER_MIB * 2**20
    if n > WORKERS_PER_CORE * c or (free is not None and need > free):
        mem = f"{free / 2**30:.1f} GiB of memory available" if free is not None else "memory unknown"
        raise InputError(f"{n} workers is far beyond this machine: {c} cores and {mem}; each worker process takes "
                         f"about {WORKER_MIB} MiB before its first run ({need / 2**30:.1f} GiB for {n}), and workers "
                         f"beyond the cores only share them: use --workers {suggested_workers()} (or fewer)")


def distributed_wanted(workers, scheduler) -> bool:
    """True when a cluster is asked for; then Dask must be installed (the ``cluster`` extra)."""
    wanted = bool(scheduler) or bool(workers)
    if wanted:
        require_dask()
    return wanted


def require_dask() -> None:
    """A clear error, before any work, when Dask's ``distributed`` is not installed."""
    import importlib.util

    if importlib.util.find_spec("distributed") is None or importlib.util.find_spec("dask") is None:
        raise InputError("running on a cluster (--workers N or --scheduler ADDRESS) needs Dask, which is not "
                         "installed: pip install 'clgs[cluster]' (or run without --workers/--scheduler, "
                         "one scan after another)")


def thread_share_plugin():
    """A Dask worker plugin that sets :func:`thread_env` in each worker of a running cluster (one
    this module did not start) before its first task: the worker's own thread count (``dask worker
    --nthreads``) is the share of the cores its runs use."""
    from distributed import WorkerPlugin

    class ThreadShare(WorkerPlugin):
        name = "clgs-thread-share"

        def setup(self, worker):
            for k, v in thread_env(worker.state.nthreads).items():
                os.environ.setdefault(k, v)

    return ThreadShare()


@contextlib.contextmanager
def open_client(workers=None, scheduler=None, echo=print):
    """A ``distributed.Client``: on a new local cluster of ``workers`` processes, or connected to
    ``scheduler``. Yields (client, resources for each task or None). Prints the dashboard link."""
    check_choice(workers, scheduler)
    require_dask()
    import dask
    from distributed import Client, LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES}):
        if scheduler:
            try:
                client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {exc}; start one "
                                 "(`dask scheduler`, then `dask worker ADDRESS`) or use --workers N") from exc
            cluster = None
        else:
            n = int(workers)
            threads = max(1, cores() // n)
            cluster = LocalCluster(n_workers=n, threads_per_worker=threads, processes=True,
                                   resources={RESOURCE: 1}, env=thread_env(threads),
                                   dashboard_address=":0", silence_logs=logging.CRITICAL)
            client = Client(cluster)
        try:
            if scheduler:
                client.register_plugin(thread_share_plugin())
                info = client.scheduler_info().get("workers", {})
                resources = {RESOURCE: 1} if info and all(
                    RESOURCE in (w.get("resources") or {}) for w in info.values()) else None
            else:
                resources = {RESOURCE: 1}
            link = getattr(client, "dashboard_link", None)
            if link and echo is not None:
                echo(f"Dask dashboard: {link}")
            yield client, resources
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
