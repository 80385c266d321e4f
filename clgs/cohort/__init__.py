"""Cohorts: many independent runs (reconstructions, registrations) as tasks, run one after
another in this process (the default) or on Dask distributed (a local cluster of worker
processes, or a running cluster's scheduler).

:mod:`clgs.cohort.runner` runs a list of tasks and gathers their outcomes (a task that raises is
an outcome with its error, never the end of the others); :mod:`clgs.cohort.cluster` starts or
joins the cluster and shares the cores between its workers; :mod:`clgs.cohort.batch` is
``clgs batch`` (scans x methods x settings); :mod:`clgs.cohort.registration` runs the model
build's per-subject registrations as tasks.

Dask is imported only when a cluster is asked for.
"""
from clgs.cohort.runner import Outcome, Task, run_tasks

__all__ = ["Task", "Outcome", "run_tasks"]
