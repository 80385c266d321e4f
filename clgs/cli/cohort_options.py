"""``--workers`` and ``--scheduler``: where the runs of a cohort command go (clgs.cohort)."""
from __future__ import annotations

import click


def cohort_options(fn):
    """Add ``--workers N`` and ``--scheduler ADDRESS`` (keyword arguments ``workers``, ``scheduler``)."""
    fn = click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
                      help="run the tasks on the running Dask cluster with this scheduler (workers read inputs "
                           "and write outputs on paths they share with this machine)")(fn)
    fn = click.option("--workers", default=0, show_default=True, type=click.IntRange(min=0),
                      help="run the tasks on a local Dask cluster of N worker processes, each with an equal share "
                           "of the cores (0: here, one after another)")(fn)
    return fn


def check_cohort_options(workers, scheduler) -> None:
    if workers and scheduler:
        raise click.UsageError("give --workers N (a local cluster) or --scheduler ADDRESS (a running one), not both")
    if scheduler is not None and "://" not in scheduler:
        raise click.BadParameter(f"{scheduler!r}: give the address as tcp://HOST:PORT", param_hint="--scheduler")
