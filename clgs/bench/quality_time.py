"""``clgs bench quality-time``: time to each quality level, the fast schedule against the paper's.

A Gaussian run is judged by the quality it reaches and the time it takes, not by its iteration
rate (:mod:`clgs.fit.schedule`). This benchmark runs one simulated scan (it must carry its truth)
under each schedule asked for, one after the other in the same process, and logs every run's 3D
PSNR / SSIM (and, for the shape-guided method, the fitted model surface's mean distance to the
true surface) against its time. It prints, per schedule, the final figures and the time at which
each level was first reached: the paper run's final 3D PSNR less 1, 0.5, 0.2 and 0.1 dB, and its
model surface plus 0.05 mm. Times are the run's own: its setup (FDK, initialisation, the shape
registration) plus its training time up to that evaluation; evaluations are left out, so the
figures do not depend on how often a run is measured.

``--reference LOG`` reads the paper run from an earlier benchmark's log (its ``log.csv`` and
``run.json``) instead of running it again: 30 000 iterations take half an hour or more on two
cores. The figures then come from two processes; the benchmark says so.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import click

from clgs.bench.host import HostWatch

PSNR_DROPS = (1.0, 0.5, 0.2, 0.1)  # dB below the paper run's final 3D PSNR
SURFACE_MARGIN_MM = 0.05  # above the paper run's final model surface


def _surface_evaluator(base, template, truth_surface):
    """``base`` (a trainer's evaluator) plus the fitted model surface's mean distance (mm) to the
    true surface, for the benchmark's log only: no run of a user reads the truth."""
    from clgs import metrics
    from clgs.io.mesh import Mesh
    from clgs.methods.shape_guided import deformed_template_surface

    def evaluate(trainer) -> dict:
        out = base(trainer)
        moved = deformed_template_surface(template, trainer.sets[0])
        if moved is not None:
            out["model_surface_mm"] = float(metrics.surface_distance(Mesh(*moved), truth_surface,
                                                                     n_samples=20000)["mean"])
        return out

    return evaluate


def run_schedule(scan, method: str, schedule: str, settings: dict, iterations: int | None, out_dir,
                 anatomy=None) -> dict:
    """One run of ``method`` (``shape`` or ``r2gs``) under ``schedule``: its log rows and figures."""
    from clgs.fit.assembly import restore
    from clgs.fit.config import run_config
    from clgs.fit.outputs import voxelize_volume

    t0 = time.perf_counter()
    settings = {**settings, "schedule": schedule}
    if method == "shape":
        from clgs.methods.shape_guided import ShapeGuidedConfig, build_trainer

        cfg, _ = run_config(ShapeGuidedConfig, iterations, settings, False, None)
        trainer = build_trainer(scan, anatomy, cfg, out_dir, progress=False)
        if scan.surface is not None:
            trainer.evaluate = _surface_evaluator(trainer.evaluate, anatomy.template, scan.surface)
    else:
        from clgs.methods.r2gs import R2GSConfig, build_trainer

        cfg, _ = run_config(R2GSConfig, iterations, settings, False, None, n_views=scan.geometry.n_views)
        trainer = build_trainer(scan, cfg, out_dir, progress=False)
    restore(trainer, None, cfg)
    setup = time.perf_counter() - t0
    trainer.fit()
    volume = voxelize_volume(trainer) / cfg.value_scale
    from clgs import metrics

    final = {k: v for k, v in metrics.volume_figures(volume, scan.truth).items() if k in ("psnr3d", "ssim3d")}
    last = trainer.log.rows[-1] if trainer.log.rows else {}
    if "model_surface_mm" in last:
        final["model_surface_mm"] = last["model_surface_mm"]
    if method == "shape" and scan.surface is not None:  # the bone surface a run writes, at its level
        from clgs.anatomy.evaluation import evaluate_volume

        figures = evaluate_volume(anatomy.anatomy, scan, volume)
        if "surface_mean_mm" in figures:
            final["volume_surface_mm"] = figures["surface_mean_mm"]
    record = {"schedule": schedule, "method": method, "iterations": trainer.iteration,
              "planned_iterations": cfg.iterations, "setup_s": setup, "training_s": trainer.seconds,
              "converged": trainer.converged, "final": final, "config": cfg.to_json(),
              "interrupted": bool(trainer.interrupted), "stop_signal": getattr(trainer, "stop_signal", None)}
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        trainer.log.write_csv(out / "log.csv")
        (out / "run.json").write_text(json.dumps(record, indent=1))
    return {**record, "rows": trainer.log.rows}


def read_reference(folder) -> dict:
    """A run written by this benchmark's ``--out`` (``run.json`` and ``log.csv``)."""
    from clgs.fit.training_log import TrainingLog

    folder = Path(folder)
    missing = [n for n in ("run.json", "log.csv") if not (folder / n).is_file()]
    if missing:
        raise click.UsageError(f"{folder} holds no {' and no '.join(missing)}: give a folder this benchmark wrote "
                               "with -o (its paper/ subfolder), e.g. --reference qt/paper")
    try:
        record = json.loads((folder / "run.json").read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise click.UsageError(f"{folder / 'run.json'} is not readable JSON ({exc}): run the schedule again") from None
    if record.get("interrupted"):  # a run stopped by a signal is not the schedule's result
        raise click.UsageError(f"{folder} holds a run stopped by a signal at iteration {record.get('iterations')} of "
                               f"{record.get('planned_iterations')}: it is no reference; run the schedule again")
    return {**record, "rows": TrainingLog.read_csv(folder / "log.csv").rows, "from": str(folder)}


def first_reached(run: dict, key: str, level: float, higher_is_better: bool = True):
    """(seconds, iteration) of the first evaluation at ``level`` or better (seconds: the run's
    setup plus its training time there), or None when it never got there."""
    for r in run["rows"]:
        v = r.get(key)
        if v is None or (isinstance(v, float) and math.isnan(v)):
            continue
        if (v >= level) if higher_is_better else (v <= level):
            return run["setup_s"] + float(r["seconds"]), int(r["iteration"])
    return None


def gain_point(run: dict, share: float = 0.99):
    """(seconds, iteration) at which a run first had ``share`` of its final 3D PSNR gain over its
    first evaluation (the start), or None without a curve."""
    rows = [r for r in run["rows"] if r.get("psnr3d") is not None]
    final = run["final"].get("psnr3d")
    if not rows or final is None:
        return None
    start = float(rows[0]["psnr3d"])
    return first_reached(run, "psnr3d", start + share * (final - start))


def levels_table(runs: list, paper: dict) -> list:
    """Rows (label, [(seconds, iteration) or None per run]) of the quality levels set by ``paper``."""
    rows = []
    top = paper["final"].get("psnr3d")
    if top is not None:
        for d in PSNR_DROPS:
            rows.append((f"3D PSNR >= {top - d:.2f} dB (final - {d:g})",
                         [first_reached(r, "psnr3d", top - d) for r in runs]))
    surf = paper["final"].get("model_surface_mm")
    if surf is not None:
        rows.append((f"model surface <= {surf + SURFACE_MARGIN_MM:.3f} mm (final + {SURFACE_MARGIN_MM:g})",
                     [first_reached(r, "model_surface_mm", surf + SURFACE_MARGIN_MM, False) for r in runs]))
    return rows


def report(runs: list, paper: dict | None) -> str:
    from clgs.progress import format_seconds as fs

    lines = []
    for r in runs:
        f = r["final"]
        conv = (f"converged at {r['converged']['iteration']}" if r.get("converged") else "ran to its end")
        parts = [f"{r['schedule']:>5s}: {r['iterations']} of {r['planned_iterations']} iterations ({conv}), "
                 f"{fs(r['setup_s'] + r['training_s'])} (setup {fs(r['setup_s'])} + training {fs(r['training_s'])})"]
        parts.append(f"3D PSNR {f.get('psnr3d', float('nan')):.2f} dB, SSIM {f.get('ssim3d', float('nan')):.4f}")
        if "model_surface_mm" in f:
            parts.append(f"model surface {f['model_surface_mm']:.3f} mm")
        if "volume_surface_mm" in f:
            parts.append(f"volume surface {f['volume_surface_mm']:.3f} mm")
        gain = gain_point(r)
        if gain is not None:
            parts.append(f"99 % of its 3D PSNR gain by {fs(gain[0])} (iteration {gain[1]})")
        if r.get("from"):
            parts.append(f"(read from {r['from']}, an earlier process)")
        lines.append("; ".join(parts))
    if paper is not None:
        names = [r["schedule"] for r in runs]
        lines.append("")
        lines.append("first reached (setup + training time, at iteration):")
        lines.append(f"  {'level':48s}" + "".join(f"{n:>22s}" for n in names))
        for label, cells in levels_table(runs, paper):
            txt = [f"{fs(c[0])} @ {c[1]}" if c else "not reached" for c in cells]
            lines.append(f"  {label:48s}" + "".join(f"{t:>22s}" for t in txt))
        total = paper["setup_s"] + paper["training_s"]
        for r in runs:
            if r is paper:
                continue
            mine = r["setup_s"] + r["training_s"]
            dp = r["final"].get("psnr3d", float("nan")) - paper["final"].get("psnr3d", float("nan"))
            msg = f"{r['schedule']} against paper: {mine / total:.3f} of its time, {dp:+.2f} dB"
            if "model_surface_mm" in r["final"] and "model_surface_mm" in paper["final"]:
                msg += f", {r['final']['model_surface_mm'] - paper['final']['model_surface_mm']:+.3f} mm"
            lines.append(msg)
    return "\n".join(lines)


@click.command("quality-time")
@click.argument("scan", type=click.Path(exists=True, file_okay=False))
@click.option("--method", "-m", type=click.Choice(["shape", "r2gs"]), default="shape", show_default=True,
              help="shape-guided (with --anatomy) or R2-Gaussian mode")
@click.option("--anatomy", default="femur", show_default=True, help="the anatomy of a shape-guided run")
@click.option("--schedules", default="paper,fast", show_default=True,
              help="schedules to run, comma-separated, in this order")
@click.option("--reference", type=click.Path(exists=True, file_okay=False), default=None,
              help="a paper run written by an earlier --out (its folder): read instead of run")
@click.option("--paper-iterations", type=click.IntRange(1), default=None,
              help="iterations of the paper run [default: 30000]")
@click.option("--fast-iterations", type=click.IntRange(1), default=None,
              help="iterations of the fast run [default: the method's fast schedule]")
@click.option("--log-every", type=click.IntRange(1), default=250, show_default=True,
              help="evaluate every N iterations (evaluations are not counted in the times)")
@click.option("--set", "pairs", multiple=True, metavar="KEY=VALUE", help="a method setting for every run")
@click.option("-o", "--out", type=click.Path(file_okay=False), default=None,
              help="folder for each run's log.csv and run.json (one subfolder per schedule)")
def main(scan, method, anatomy, schedules, reference, paper_iterations, fast_iterations, log_every, pairs, out):
    """Time to each quality level for the paper's schedule and the fast one, side by side.

    SCAN: a simulated scan folder (it has the truth), e.g. `clgs femur simulate --subject 20 --views 5 -o femur20_5v`.
    """
    from clgs.errors import InputError
    from clgs.io.scan import Scan
    from clgs.methods.settings import parse_pairs

    watch = HostWatch()
    s = Scan.load(scan)
    if s.truth is None:
        raise click.UsageError(f"{scan} has no truth volume: the benchmark needs a simulated scan")
    settings = {"log_every": log_every, "log_early": True, "checkpoint_every": 0, "uncertainty": "off",
                **parse_pairs(pairs)}
    parts = None
    if method == "shape":
        from clgs.anatomy import AnatomyParts, plugins

        parts = AnatomyParts.of(plugins.get_anatomy(anatomy))
    else:
        settings.pop("uncertainty")
    names = [n.strip() for n in schedules.split(",") if n.strip()]
    bad = [n for n in names if n not in ("paper", "fast")]
    if bad or not names:
        raise click.BadParameter(f"schedules are paper and fast, got {schedules!r}", param_hint="--schedules")
    runs, paper = [], None
    if reference is not None:
        paper = read_reference(reference)
        runs.append(paper)
        names = [n for n in names if n != "paper"]
    for name in names:
        iters = paper_iterations if name == "paper" else fast_iterations
        where = None if out is None else Path(out) / name
        click.echo(f"running the {name} schedule ...", err=True)
        try:
            run = run_schedule(s, method, name, settings, iters, where, anatomy=parts)
        except InputError as exc:
            raise click.UsageError(str(exc)) from None
        runs.append(run)
        if name == "paper":
            paper = run
        if run["interrupted"]:  # stopped by Ctrl-C or SIGTERM: no other schedule starts
            import signal

            sig = int(run["stop_signal"] or signal.SIGINT)
            click.echo(f"the {name} run was stopped by {signal.Signals(sig).name} at iteration {run['iterations']} of "
                       f"{run['planned_iterations']}; its figures so far follow" + (
                           f" ({where}/run.json says it was interrupted)" if where is not None else ""), err=True)
            click.echo(report(runs, paper))
            raise SystemExit(128 + sig)
    click.echo(f"{method} on {scan}: {s.geometry.n_views} views")
    click.echo(report(runs, paper))
    click.echo(watch.summary())
