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
    """The library's one check (:func:`clgs.cohort.cluster.check_choice`), before any work: a
    malformed choice is a usage error (exit 2), more workers than the machine holds an error (1)."""
    from clgs.cohort.cluster import check_form, check_workers
    from clgs.errors import InputError

    try:
        check_form(workers or None, scheduler)
    except InputError as exc:
        raise click.UsageError(str(exc)) from exc
    if workers and not scheduler:
        check_workers(workers)
