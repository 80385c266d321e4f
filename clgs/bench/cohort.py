"""``clgs bench cohort``: what a cohort costs, per task and per worker count.

1. Per task: each method of the experiment (at its settings: ``--iterations``, every view count)
   and one registration of the model build, each run alone in a fresh process, exactly as a
   worker runs it (:func:`clgs.experiment.run_and_record`,
   :func:`clgs.cohort.registration.register_subject_task`): wall time and the process's peak
   resident memory. These are the figures to plan a cluster with (memory per worker, tasks per hour).
2. Throughput: the same batch of runs (``--runs`` reconstructions of simulated scans) with 1 and
   with 2 worker processes of a local cluster (each a fresh cluster: start-up included, as a user
   sees it), side by side: runs per minute and the speed-up.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import click

from .host import HostWatch

_TASK = """
import json, resource, sys, time
from pathlib import Path
spec = json.loads(sys.argv[1])
from clgs.cohort.runner import call_task
t0 = time.perf_counter()
if spec["kind"] == "registration":
    from clgs.anatomy import plugins
    from clgs.cohort.registration import register_subject_task
    from clgs.shape.registration import RegistrationSettings
    anatomy = plugins.get_anatomy(spec["anatomy"])
    bs = dict(getattr(getattr(anatomy, "population_model", None), "builder_settings", {}) or {})
    job = {"id": spec["subject"], "cache_path": str(Path(spec["out"]) / "registration.npz"),
           "max_cells": int(bs.get("max_cells", 64)),
           "registration": RegistrationSettings.from_dict(bs.get("registration")).to_dict(), "atlas": True,
           "threads": 1, "template_hash": anatomy.load_template().content_hash()}
    raw = call_task(register_subject_task, (spec["anatomy"], job), {})
else:
    from clgs.experiment import run_and_record
    (Path(spec["out"]) / "runs").mkdir(parents=True, exist_ok=True)
    per_run = {"log_every": 0, "checkpoint_every": 0}
    raw = call_task(run_and_record, (), dict(anatomy=spec["anatomy"], subject_id=spec["subject"],
                    views=spec["views"], method=spec["method"], iterations=spec["iterations"], seed=0,
                    settings={"r2gs": per_run, "shape": per_run}, out_dir=spec["out"]))
result = raw.get("result") or {}
print("RESULT " + json.dumps({"seconds": time.perf_counter() - t0, "error": raw.get("error"),
      "psnr3d": result.get("psnr3d") if isinstance(result, dict) else None,
      "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))
"""


def _one_task(spec: dict) -> dict:
    """Run one task in a fresh Python process; its figures."""
    with tempfile.TemporaryDirectory(prefix="clgs-bench-cohort-") as tmp:
        spec = dict(spec, out=tmp)
        r = subprocess.run([sys.executable, "-c", _TASK, json.dumps(spec)], capture_output=True, text=True)
    lines = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")]
    if r.returncode != 0 or not lines:
        return {"error": (r.stderr.strip().splitlines() or ["no output"])[-1]}
    return json.loads(lines[-1][len("RESULT "):])


def _per_task(anatomy, subject, views, methods, iterations, registration: bool) -> None:
    click.echo(f"\nper task, each alone in a fresh process ({anatomy.name}, subject {subject}, {iterations} "
               "iterations for the Gaussian methods):")
    click.echo(f"  {'task':34s} {'wall s':>8s} {'peak MiB':>9s} {'3D PSNR':>8s}")
    specs = [(f"{m} {v} views", {"kind": "run", "anatomy": anatomy.name, "subject": subject, "views": v,
                                 "method": m, "iterations": iterations}) for v in views for m in methods]
    if registration and anatomy.population is not None:
        sid = anatomy.population()[0]
        specs.append((f"registration of subject {sid}", {"kind": "registration", "anatomy": anatomy.name,
                                                         "subject": sid}))
    for label, spec in specs:
        r = _one_task(spec)
        if r.get("error"):
            click.echo(f"  {label:34s} failed: {r['error']}")
            continue
        psnr = "-" if r.get("psnr3d") is None else f"{r['psnr3d']:.2f}"
        click.echo(f"  {label:34s} {r['seconds']:8.1f} {r['peak_mib']:9.0f} {psnr:>8s}")


def _throughput(anatomy, subject, view, method, runs, iterations, counts) -> None:
    import math

    from clgs.anatomy.simulation import simulate_subject
    from clgs.cohort.batch import run_batch

    click.echo(f"\nthroughput: the same {runs} {method} runs ({anatomy.name} subject {subject}, {view} views, "
               f"seeds 0-{runs - 1}" + (f", {iterations} iterations" if method != "fdk" else "") + "):")
    with tempfile.TemporaryDirectory(prefix="clgs-bench-cohort-") as tmp:
        scan_dir = os.path.join(tmp, "scan")
        simulate_subject(anatomy, anatomy.load_subject(subject), view, math.pi, True, 0).save(scan_dir)
        settings = {} if method == "fdk" else {"iterations": iterations, "log_every": 0, "checkpoint_every": 0}
        batch = [{"scan": scan_dir, "method": method, "seed": i, "settings": settings, "out": f"run{i}"}
                 for i in range(runs)]
        figures = {}
        for n in counts:
            t0 = time.perf_counter()
            summary = run_batch(batch, os.path.join(tmp, f"w{n}"), workers=n, progress=False, echo=lambda *_: None)
            wall = time.perf_counter() - t0
            done = [r for r in summary["runs"] if r["status"] == "done"]
            peaks = []
            for r in done:
                with open(os.path.join(r["out"], "run.json")) as f:
                    peaks.append(json.load(f).get("process_peak_mib"))
            figures[n] = (wall, len(done), sum(r["seconds"] for r in done) / max(1, len(done)),
                          max((p for p in peaks if p), default=float("nan")))
        click.echo(f"  {'workers':>7s} {'wall s':>8s} {'runs/min':>9s} {'s per run':>10s} {'worker peak MiB':>16s}")
        base = None
        for n, (wall, done, per_run, peak) in figures.items():
            rate = 60.0 * done / wall
            base = base or rate
            click.echo(f"  {n:7d} {wall:8.1f} {rate:9.2f} {per_run:10.1f} {peak:16.0f}   x{rate / base:.2f}")


@click.command()
@click.option("--anatomy", "anatomy_name", default="femur", show_default=True, help="an installed anatomy")
@click.option("--subject", default=None, help="held-out subject [default: the first]")
@click.option("--views", multiple=True, type=click.IntRange(min=1), help="view counts per task [default: 5 10]")
@click.option("--methods", default="fdk,r2gs,shape", show_default=True, help="methods timed per task")
@click.option("--iterations", default=1000, show_default=True, type=click.IntRange(min=1),
              help="iterations of the per-task Gaussian runs (the experiment's default)")
@click.option("--registration/--no-registration", default=True, show_default=True,
              help="time one registration of the model build")
@click.option("--per-task/--no-per-task", default=True, show_default=True, help="the per-task figures")
@click.option("--runs", default=4, show_default=True, type=click.IntRange(min=0),
              help="runs of the throughput batch (0: none)")
@click.option("--runs-method", default="r2gs", show_default=True, help="method of the throughput batch")
@click.option("--runs-iterations", default=100, show_default=True, type=click.IntRange(min=1),
              help="iterations of each throughput run")
@click.option("--workers", "counts", multiple=True, type=click.IntRange(min=1),
              help="worker counts compared [default: 1 2]")
def main(anatomy_name, subject, views, methods, iterations, registration, per_task, runs, runs_method,
         runs_iterations, counts):
    """Time and peak memory per cohort task; runs per minute with 1 and 2 workers on the same runs."""
    from clgs.anatomy import plugins
    from clgs.cohort.cluster import cores

    anatomy = plugins.get_anatomy(anatomy_name)
    subject = subject or anatomy.test_subjects()[0]
    views = tuple(views) or (5, 10)
    watch = HostWatch()
    click.echo(f"clgs bench cohort: {cores()} cores here")
    if per_task:
        _per_task(anatomy, subject, views, [m.strip() for m in methods.split(",") if m.strip()], iterations,
                  registration)
    if runs:
        _throughput(anatomy, subject, views[0], runs_method, runs, runs_iterations, tuple(counts) or (1, 2))
    click.echo(watch.summary())
