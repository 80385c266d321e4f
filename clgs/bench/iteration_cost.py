"""``clgs bench iteration-cost``: what an R2-Gaussian iteration costs on the Gaussians a run has
trained, under the run's own settings and under variants of them, side by side.

Why: an iteration's cost depends on the scene it works on. A run's Gaussians grow and widen as it
trains (on a 128^3 thorax an iteration costs about 50 ms at the start and 85-95 ms late, most of it
the TV patch, which voxelises every Gaussian that reaches its block), so the synthetic scene of
``clgs bench train`` says little about a real run's late iterations. This benchmark loads a run's
checkpoint (``clgs reconstruct --method r2gs --out RUN``, or a ``clgs bench quality-time -o``
subfolder), builds one trainer per setting variant on the same Gaussians and scan, and times them
in alternating blocks of iterations in one process, so a busy host slows every variant alike. It
prints the median milliseconds per iteration of each variant and its ratio to the run's own.
Quality is not measured here: what a variant costs in 3D PSNR is ``clgs bench quality-time``'s.
"""
from __future__ import annotations

import statistics
from pathlib import Path

import click

from clgs.bench.host import HostWatch


def trained_scene(run_dir, scan):
    """(settings JSON, [means, scales, quats, densities] as numpy, training units, iteration) of the
    R2-Gaussian run whose ``checkpoint.pt`` is in ``run_dir``, trained on ``scan``."""
    from clgs.errors import InputError
    from clgs.fit import checkpoint as ckpt
    from clgs.fit.assembly import restore
    from clgs.methods.r2gs import R2GSConfig, build_trainer

    path = Path(run_dir) / "checkpoint.pt"
    if not path.is_file():
        raise click.UsageError(f"{run_dir} holds no checkpoint.pt: give the folder of an R2-Gaussian run "
                               "(clgs reconstruct --method r2gs --out RUN)")
    state = ckpt.load(path)
    saved = ckpt.loads(state["config"])
    try:
        cfg = R2GSConfig.from_json(saved)
    except (InputError, TypeError, ValueError) as exc:  # a shape-guided run's settings, or damaged ones
        raise click.UsageError(f"{path} is not an R2-Gaussian run's checkpoint ({exc})") from None
    trainer = build_trainer(scan, cfg, state=state)
    restore(trainer, state, cfg)
    scene = [t.detach().numpy().copy() for t in trainer.scene_tensors()]
    return saved, scene, int(state["iteration"])


def variant_trainer(scan, settings: dict, scene, iteration: int):
    """A trainer of ``settings`` on ``scene``'s Gaussians, at ``iteration`` (its learning rates and
    densification as the run has them there), without evaluations or checkpoints."""
    from clgs.methods.r2gs import R2GSConfig, build_trainer

    cfg = R2GSConfig.from_json({**settings, "log_every": 0, "checkpoint_every": 0})
    cfg.iterations = max(cfg.iterations, iteration + 1)
    trainer = build_trainer(scan, cfg, gaussians=scene)
    trainer.evaluate = None
    trainer.iteration = iteration
    return trainer


@click.command("iteration-cost")
@click.argument("run", type=click.Path(exists=True, file_okay=False))
@click.option("--scan", "scan_dir", required=True, type=click.Path(exists=True, file_okay=False),
              help="the scan folder the run was trained on")
@click.option("--variant", "variants", multiple=True, metavar="KEY=VALUE[,KEY=VALUE]",
              help="settings changed from the run's (repeat for more variants), e.g. tv_every=4")
@click.option("--at-iteration", type=click.IntRange(min=0), default=None,
              help="time the iterations from this one on [default: the end of densification or the "
                   "checkpoint's iteration, the later]")
@click.option("--rounds", type=click.IntRange(min=1), default=6, show_default=True,
              help="alternating rounds (each variant once per round)")
@click.option("--block", type=click.IntRange(min=1), default=8, show_default=True,
              help="iterations per variant per round")
def main(run, scan_dir, variants, at_iteration, rounds, block):
    """ms per iteration on a trained run's Gaussians, its settings against variants, side by side.

    RUN: the folder of an R2-Gaussian run (it holds checkpoint.pt).
    """
    import os

    import torch

    from clgs import runtime
    from clgs.bench.train import time_steps
    from clgs.errors import InputError
    from clgs.io.scan import Scan
    from clgs.methods.settings import parse_pairs

    watch = HostWatch()
    scan = Scan.load(scan_dir)
    saved, scene, done = trained_scene(run, scan)
    at = max(int(saved.get("densify_until", 0)), done) if at_iteration is None else at_iteration
    cases = [("the run's settings", {})]
    for text in variants:
        cases.append((text, parse_pairs([p for p in text.split(",") if p.strip()])))
    try:
        trainers = [variant_trainer(scan, {**saved, **change}, scene, at) for _, change in cases]
    except InputError as exc:
        raise click.UsageError(str(exc)) from None
    click.echo(f"scene: {len(scene[0])} Gaussians of {run} (trained {done} iterations), "
               f"{'x'.join(map(str, scan.geometry.nDetector))} detector, {scan.geometry.n_views} views; "
               f"timed from iteration {at} on")
    click.echo(f"device: {runtime.device_label()}; torch threads: {torch.get_num_threads()}; "
               f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (others' work slows every figure)")
    times: list[list[float]] = [[] for _ in cases]
    for t in trainers:  # the first iterations build the kernels
        time_steps(t, 1, warmup=1)
    for _ in range(rounds):
        for k, t in enumerate(trainers):
            times[k].append(time_steps(t, block, warmup=0))
    base = statistics.median(times[0])
    click.echo(f"{rounds} alternating rounds of {block} iterations each; median ms per iteration:")
    click.echo(f"  {'settings':44s}{'ms / it':>10s}{'speed-up':>10s}")
    for (name, _), ts in zip(cases, times):
        ms = statistics.median(ts)
        click.echo(f"  {name:44s}{ms * 1e3:10.1f}{base / ms:9.2f}x")
    click.echo(watch.summary())
