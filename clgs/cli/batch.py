"""``clgs batch``: reconstruct many scans with many methods and settings (:mod:`clgs.cohort.batch`),
here or on a Dask cluster."""
from __future__ import annotations

from pathlib import Path

import click

from clgs.cli.cohort_options import check_cohort_options, cohort_options
from clgs.cli.options import Seed, out_option
from clgs.cli.verbosity import info


def _checked_settings(runs) -> None:
    """Every run's KEY=VALUE settings checked as ``clgs reconstruct --set`` checks them (before any
    run starts), replaced by the values the method takes."""
    from clgs import methods
    from clgs.cli.settings import check_settings, parse_settings

    for r in runs:
        try:
            m = methods.get(r["method"])
            fn = m.callable()
        except LookupError as exc:
            raise click.BadParameter(f"run on {r['scan']}: {exc}", param_hint="method") from None
        raw: dict = {}
        try:
            r["settings"] = check_settings(r["method"], m, fn, parse_settings(r["settings"], raw), raw)
        except click.BadParameter as exc:
            raise click.BadParameter(f"run on {r['scan']} with {r['method']}: {exc.message}",
                                     param_hint="settings") from None


def _settings_for(method: str, pairs) -> list:
    """The ``--set`` pairs that ``method`` takes (a folder batch's settings go to the methods that
    know them: ``iterations=`` to r2gs, not to fdk)."""
    from clgs import methods
    from clgs.cli.settings import method_settings

    m = methods.get(method)
    hints, _, open_, _ = method_settings(method, m, m.callable())
    return [p for p in pairs if open_ or p.partition("=")[0].strip().replace("-", "_") in hints]


@click.command()
@click.argument("source", type=click.Path(exists=True, path_type=Path))
@out_option(required=True, type=click.Path(file_okay=False, path_type=Path),
            help="batch folder: one folder per run, summary.csv and summary.json (a batch run again resumes)")
@click.option("--method", "-m", "method_names", multiple=True,
              help="with a folder of scans: method(s) to run on every scan (repeatable) [default: fdk]")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="with a folder of scans: a setting of every run (repeatable), as clgs reconstruct --set")
@click.option("--seed", type=Seed(), default=None, help="with a folder of scans: every run's seed")
@click.option("--progress/--no-progress", default=True, show_default=True, help="a progress bar over runs")
@cohort_options
def batch(source, out, method_names, settings, seed, progress, workers, scheduler):
    """Reconstruct many scans: SOURCE is a folder of scan folders (every --method on every scan) or a
    .csv/.json list with columns scan, method and optional settings (KEY=VALUE;KEY=VALUE), seed, out.

    Each run writes its own folder (volume.npy, volume.nii.gz, the method's files, run.json) as it
    ends; runs finished before are kept. Prints and writes the summary (summary.csv, summary.json),
    with the error of each run that failed (exit status 1 then)."""
    from clgs.cohort.batch import read_list, run_batch, scan_folders

    check_cohort_options(workers, scheduler)
    if source.is_dir() and (source / "scan.json").is_file():
        raise click.BadParameter(f"{source} is a scan folder; give a folder of scan folders or a .csv/.json list",
                                 param_hint="SOURCE")
    if source.is_dir():
        names = list(method_names) or ["fdk"]
        try:
            per_method = {m: _settings_for(m, settings) for m in names}
        except LookupError as exc:
            raise click.BadParameter(str(exc), param_hint="--method") from None
        unused = [p for p in settings if not any(p in v for v in per_method.values())]
        if unused:
            raise click.BadParameter(f"{', '.join(unused)}: no method of {', '.join(names)} takes it",
                                     param_hint="--set")
        runs = [{"scan": s, "method": m, "settings": per_method[m], "seed": seed, "out": None}
                for s in scan_folders(source) for m in names]
    else:
        given = [o for o, v in (("--method", method_names), ("--set", settings), ("--seed", seed is not None)) if v]
        if given:
            raise click.UsageError(f"{', '.join(given)}: with a list, each row gives its method, settings and seed")
        runs = read_list(source)
    _checked_settings(runs)
    summary = run_batch(runs, out, workers=workers or None, scheduler=scheduler, progress=progress, echo=info)
    for r in summary["runs"]:
        figures = "" if r.get("psnr3d") is None else f", PSNR {r['psnr3d']:.2f} dB, SSIM {r['ssim3d']:.4f}"
        seconds = "" if r.get("seconds") is None else f", {r['seconds']:.1f} s"
        click.echo(f"  {r['name']}: {r['status']}{figures}{seconds}" + (f": {r['error']}" if r.get("error") else ""))
    c = summary["counts"]
    click.echo(f"batch: {c['done']} done, {c['kept']} kept, {c['failed']} failed"
               + (f", {c['interrupted']} interrupted" if c.get("interrupted") else "") + f" -> {out / 'summary.csv'}")
    if summary.get("stop_signal"):
        import signal

        sig = int(summary["stop_signal"])
        click.echo(f"batch stopped by {signal.Signals(sig).name}: the run going on saved its checkpoint (FDK and SART "
                   "runs are cut) and is recorded as interrupted; the same command resumes the batch", err=True)
        raise SystemExit(128 + sig)
    if c["failed"]:
        raise click.ClickException(f"{c['failed']} run(s) failed (errors in {out / 'summary.csv'}); the others are "
                                   "done: run the same command again to retry them")
