"""The model build's per-subject registrations as tasks (``clgs <anatomy> build-model --workers N``).

:func:`clgs.shape.builder.build_model` hands the subjects it has no cached registration for to a
``run_registrations`` callable; :func:`registration_runner` makes one that runs each as a task of
:func:`clgs.cohort.runner.run_tasks`. A task loads the anatomy (an installed plugin, by name), its
template and the subject itself, checks that its template is the build's (same content hash),
registers with the build's settings and writes the subject's cache entry; the build then reads the
entries as if it had made them. A failed registration is reported after the others have finished
(their entries are kept, so the next build resumes).
"""
from __future__ import annotations

from clgs.errors import InputError

# the latest template and its distance field of this process (a worker registers many subjects)
_TEMPLATE: dict = {}


def register_subject_task(anatomy_name: str, job: dict) -> dict:
    """One registration in a worker: ``job`` as :func:`clgs.shape.builder.build_model` gives it;
    returns the subject's registration residuals."""
    from clgs.anatomy import plugins
    from clgs.shape.builder import register_subject, template_distance
    from clgs.shape.template import json_from_array

    anatomy = plugins.get_anatomy(anatomy_name)
    key = (anatomy_name, job["template_hash"], job["max_cells"])
    if _TEMPLATE.get("key") != key:
        _TEMPLATE.clear()
        template = anatomy.load_template()
        if template.content_hash() != job["template_hash"]:
            raise InputError(f"the {anatomy_name} template in this worker ({template.content_hash()}) is not the "
                             f"build's ({job['template_hash']}): workers must run the same plugin version and data")
        _TEMPLATE.update(key=key, template=template, fixed=template_distance(template, job["max_cells"]))
    subject = anatomy.load_subject(job["id"])
    record = register_subject(_TEMPLATE["template"], subject, job["id"], job["cache_path"], job["max_cells"],
                              job["registration"], job["atlas"], job["threads"], fixed=_TEMPLATE["fixed"])
    return json_from_array(record["metadata"])["residuals"]


def registration_runner(anatomy_name: str, workers: int | None = None, scheduler: str | None = None,
                        progress: bool = True, echo=print):
    """A ``run_registrations`` callable for :func:`clgs.shape.builder.build_model` that runs the
    registrations as tasks (here one after another, or on Dask: ``workers``, ``scheduler``)."""
    from clgs.cohort.runner import Task, run_tasks

    def run(jobs):
        tasks = [Task(f"register-{job['id']}", register_subject_task, (anatomy_name, job)) for job in jobs]
        outcomes = run_tasks(tasks, workers=workers, scheduler=scheduler, desc="registrations", progress=progress,
                             echo=echo)
        failed = [o for o in outcomes if not o.ok]
        if failed:
            raise InputError(f"{len(failed)} of {len(jobs)} registrations failed (the others are cached, a new build "
                             "resumes from them): " + "; ".join(f"{o.key[len('register-'):]}: {o.error}"
                                                                 for o in failed))

    return run
