"""``clgs bench train``: training iterations per second, OpenCL against the same iteration in torch.

``--method r2gs`` (default) times R2-Gaussian mode on a synthetic scene (below); ``--method shape``
times the shape-guided method on an anatomy's held-out subject as ``clgs <anatomy> demo`` runs it
(the femur: 35k shape-guided + 15k free Gaussians, 5 views). Both print where an iteration goes:
torch's profiler over a few iterations, each OpenCL operator's forward and backward (the autograd
functions named after them), torch's own operations, Adam, and the rest (Python, autograd's
bookkeeping), per iteration; and the process's peak resident memory. With ``--method shape``,
``--alternate N`` also times each speed step of that iteration against the code before it, side by
side on the same trainer (``clgs.bench.switches``), and ``--at-iteration K`` times the iterations
as the 30 000-iteration run has them from iteration K on (late, alpha's learning rate is low).

One iteration is exactly what ``clgs reconstruct --method r2gs`` runs: learning rates from their
schedules, one view, projection, L1 + 0.25 D-SSIM + 0.05 TV on a voxelised random 32^3 patch,
backward, Adam, densification statistics. The scene: N Gaussians (default 50 000, 3-sigma radii of
about 2-8 detector pixels) in a 128^3 volume, a 256^2 cone-beam detector, 50 views; the targets are
the projections of a perturbed copy of the model. Both backends run in the same process, one after
the other (torch for fewer iterations), so their ratio is measured under the same machine load.
"""
from __future__ import annotations

import click

from clgs.bench.devices import device_option, on_each_device, ratio_table
from clgs.bench.host import HostWatch


def synthetic_scene(n: int, n_detector: int, n_voxel: int, n_views: int, mode: str, seed: int,
                    sized_for: int | None = None):
    """(geometry, scan, Gaussians) of the benchmark scene: ``n`` Gaussians whose 3-sigma radii are
    2-8 pixels of a ``sized_for`` detector (default: this one), in a 256 mm volume."""
    import numpy as np
    import torch

    from clgs.geometry import Geometry
    from clgs.io.scan import Scan
    from clgs.ops.projector import project

    geo = Geometry.default(n_views=n_views, n_voxel=n_voxel, n_detector=n_detector, volume_mm=256.0, mode=mode)
    rng = np.random.default_rng(seed)
    box = 0.5 * geo.sVoxel[::-1] * geo.scale
    # pixels per scene unit at the rotation axis, to size the footprints in detector pixels
    px = (geo.DSD / geo.DSO if mode == "cone" else 1.0) / (geo.dDetector[1] * geo.scale)
    if sized_for is not None:  # the same objects seen by a finer or coarser detector
        px *= sized_for / n_detector
    means = (rng.random((n, 3)) * 1.6 - 0.8) * box
    scales = rng.uniform(2.0, 8.0, (n, 1)) / 3.0 / px * rng.uniform(0.7, 1.3, (n, 3))
    quats = rng.normal(size=(n, 4))
    dens = rng.uniform(0.2, 1.0, n)
    truth = [torch.tensor(a, dtype=torch.float32) for a in
             (means + rng.normal(0, 0.003, means.shape), scales, quats, dens * rng.uniform(0.8, 1.2, n))]
    with torch.no_grad():
        proj = torch.cat([project(*truth, geo, list(range(i, min(i + 10, n_views))))
                          for i in range(0, n_views, 10)]).numpy()
    return geo, Scan(geo, proj), (means, scales, quats, dens)


def r2gs_trainer(scan, gaussians, backend: str, seed: int):
    from clgs.methods.r2gs import R2GSConfig, build_trainer

    cfg = R2GSConfig(iterations=30_000, backend=backend, seed=seed, value_scale=1.0, log_every=0, checkpoint_every=0)
    t = build_trainer(scan, cfg, gaussians=gaussians)
    t.evaluate = None
    return t


def time_steps(trainer, n: int, warmup: int) -> float:
    """Seconds per iteration, with the torch thread setting ``fit`` would use."""
    import time

    import torch

    threads = torch.get_num_threads()
    if trainer.torch_threads:
        torch.set_num_threads(trainer.torch_threads)
    try:
        for _ in range(warmup):
            trainer.step()
        t0 = time.perf_counter()
        for _ in range(n):
            trainer.step()
        return (time.perf_counter() - t0) / n
    finally:
        torch.set_num_threads(threads)


def _breakdown(trainer, n: int = 10) -> dict:
    """ms per iteration of each part of an OpenCL iteration, forward + backward, measured alone on
    the trainer's model (its state is left as it was, but for the densifier's statistics)."""
    import time

    import torch

    from clgs.fit import losses as L
    from clgs.fit.trainer import Context
    from clgs.fit.tv_patch import tv_patch
    from clgs.ops import ssim as ssim_cl
    from clgs.ops.projector import project_packed
    from clgs.ops.voxelizer import cov_prec

    geo = trainer.geometry
    view = trainer.views[0]
    threads = torch.get_num_threads()
    if trainer.torch_threads:
        torch.set_num_threads(trainer.torch_threads)
    leaf = lambda t: t.detach().clone().requires_grad_(True)  # noqa: E731
    with torch.no_grad():
        means, scales, quats, dens = (t.detach() for t in trainer.scene_tensors())
        cov, prec, extent = cov_prec(scales, quats, extent=True)
    ins = [leaf(means), leaf(cov), leaf(dens)]
    sq = [leaf(scales), leaf(quats)]
    vox = [leaf(means), leaf(prec), leaf(dens)]
    target = trainer.projections[view]
    image_target = ssim_cl.SSIMTarget(target, L.target_maps(target))  # as the trainer caches it per view
    render = leaf(trainer.backend.project(means, scales, quats, dens, geo, [view])[0] * trainer.render_scale)
    grid = geo.volume_grid(scene=True)
    params = [p.detach().clone() for g in trainer.optimizer.param_groups for p in g["params"]]
    for p in params:
        p.grad = torch.randn_like(p)
    try:
        adam = torch.optim.Adam([{"params": [p]} for p in params], eps=1e-15, fused=True)
    except (RuntimeError, TypeError, ValueError):
        adam = torch.optim.Adam([{"params": [p]} for p in params], eps=1e-15)
    densifier = next((h for h in trainer.hooks if hasattr(h, "after_backward")), None)
    ctx = Context(trainer, view)
    for s in trainer.sets:  # gradients for the densifier's statistics
        for p in s.params.values():
            p.grad = torch.randn_like(p)

    def image_terms():  # the trainer's OpenCL path (clgs.fit.losses.ImageTerms): one fused op, both terms
        l1, dssim = ssim_cl.l1_dssim(render, image_target)
        (l1 + 0.25 * dssim).backward()

    def activations():
        sum(t.sum() for s in trainer.sets for t in s.tensors()).backward()

    parts = {
        "activations": activations,
        # as trained: covariance, precision and half-widths in one pass, both gradients back
        "covariance + precision (N,6)": lambda: sum(m.sum() for m in cov_prec(*sq)[:2]).backward(),
        "projection kernels": lambda: project_packed(*ins, geo, [view]).sum().backward(),
        "L1 + D-SSIM": image_terms,
        "TV 32^3 patch (cull, kernels)": lambda: tv_patch(
            vox[0], vox[1], vox[2], extent, L.random_block(grid, 32, trainer.generator)).backward(),
        "Adam": adam.step,
    }
    if densifier is not None:
        parts["densification statistics"] = lambda: densifier.after_backward(trainer, ctx)
    out = {}
    try:
        for name, f in parts.items():
            f()
            t0 = time.perf_counter()
            for _ in range(n):
                f()
            out[name] = (time.perf_counter() - t0) / n
    finally:
        torch.set_num_threads(threads)
        trainer.optimizer.zero_grad(set_to_none=True)
    return out


@click.command()
@click.option("--gaussians", "n", default=50_000, show_default=True, help="number of Gaussians")
@click.option("--detector", "n_detector", default=256, show_default=True, help="detector pixels per side")
@click.option("--voxels", "n_voxel", default=128, show_default=True, help="volume voxels per side")
@click.option("--views", "n_views", type=click.IntRange(min=1), default=None,
              help="projections [default: 50 for r2gs, 5 for shape (the demo's)]")
@click.option("--mode", type=click.Choice(["cone", "parallel"]), default="cone", show_default=True)
@click.option("--iterations", default=200, show_default=True, help="timed OpenCL iterations")
@click.option("--torch-iterations", default=2, show_default=True, help="timed torch iterations (0: skip)")
@click.option("--seed", default=0, show_default=True)
@click.option("--method", type=click.Choice(["r2gs", "shape"]), default="r2gs", show_default=True,
              help="r2gs: R2-Gaussian mode on the synthetic scene; shape: the shape-guided method on an "
                   "anatomy's held-out subject (--anatomy, --subject; --views counts its projections)")
@click.option("--anatomy", default="femur", show_default=True, help="with --method shape")
@click.option("--subject", default=None, help="with --method shape: a held-out subject [default: the demo's]")
@click.option("--alternate", "rounds", type=click.IntRange(min=0), default=0, show_default=True,
              help="with --method shape: also time each speed step against the code before it, side by side "
                   "on the same trainer, in this many alternating pairs of 5-iteration blocks (0: skip)")
@click.option("--at-iteration", "at_iteration", type=click.IntRange(min=0), default=0, show_default=True,
              help="with --method shape: time the iterations as the default 30 000-iteration run has them from this "
                   "iteration on (learning rates from their schedules there: late, alpha moves slowly)")
@device_option
def main(n, n_detector, n_voxel, n_views, mode, iterations, torch_iterations, seed, method, anatomy, subject, rounds,
         at_iteration, devices):
    """Training iterations per second (OpenCL vs plain torch on the CPU, same iteration), and
    where an iteration goes."""
    if method != "shape" and (rounds or at_iteration):
        raise click.UsageError("--alternate and --at-iteration go with --method shape")
    runs = []  # torch is timed once, on the first device's run: it does not depend on the device

    def one():
        runs.append(None)
        if method == "shape":
            return _bench_shape(anatomy, subject, n_views or 5, iterations, seed, rounds, at_iteration)
        torch_its = torch_iterations if len(runs) == 1 else 0
        return _bench(n, n_detector, n_voxel, n_views or 50, mode, iterations, torch_its, seed)

    results = on_each_device(devices, one)
    ratio_table(results, ("ms / it", "it / s"))


def _bench(n, n_detector, n_voxel, n_views, mode, iterations, torch_iterations, seed):
    """One device's run of :func:`main`; returns {"iteration": (ms, it/s)}."""
    import torch

    from clgs import runtime

    watch = HostWatch()
    geo, scan, gaussians = synthetic_scene(n, n_detector, n_voxel, n_views, mode, seed)
    click.echo(f"scene: {n} Gaussians, {n_detector}^2 detector, {n_voxel}^3 volume, {n_views} {mode}-beam views; "
               f"loss L1 + 0.25 D-SSIM + 0.05 TV(32^3 patch), Adam")
    import os

    click.echo(f"device: {runtime.device_label()}; torch threads: {torch.get_num_threads()}; "
               f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (others' work slows every figure)")
    cl = r2gs_trainer(scan, gaussians, "cl", seed)
    t_cl = time_steps(cl, iterations, warmup=5)
    rows = [(f"OpenCL, {cl.torch_threads or torch.get_num_threads()} thr", iterations, t_cl)]
    if torch_iterations > 0:
        # torch's best thread setting counts: all cores, and one (faster when the cores are busy)
        t_torch = None
        for threads in sorted({torch.get_num_threads(), 1}, reverse=True):
            tt = r2gs_trainer(scan, gaussians, "torch", seed)
            tt.torch_threads = threads
            t = time_steps(tt, torch_iterations, warmup=1)
            rows.append((f"torch, {threads} thr", torch_iterations, t))
            t_torch = t if t_torch is None else min(t_torch, t)
    click.echo(f"{'backend':14s}{'iterations':>12s}{'ms / it':>12s}{'it / s':>10s}")
    for name, k, t in rows:
        click.echo(f"{name:14s}{k:12d}{t * 1e3:12.1f}{1.0 / t:10.1f}")
    its = 1.0 / t_cl
    line = f"OpenCL: {its:.1f} it/s (target >= 60)"
    if torch_iterations > 0:
        line += f"; speed-up over torch (its best setting): {t_torch / t_cl:.1f}x (target >= 40x)"
    click.echo(line)
    parts = _breakdown(cl)
    rest = t_cl - sum(parts.values())
    click.echo("OpenCL iteration, ms (each part forward + backward, timed alone): "
               + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in parts.items())
               + f", the rest (autograd, bookkeeping, load) {rest * 1e3:.1f}")
    click.echo(f"30 000 iterations (R2-Gaussian's default) would take {30_000 * t_cl / 60:.1f} min here")
    _echo_profile(cl, t_cl)
    click.echo(watch.summary())
    return {"training iteration": (t_cl * 1e3, 1.0 / t_cl)}


def _bench_shape(anatomy_name, subject, n_views, iterations, seed, rounds=0, at_iteration=0):
    """The shape-guided method's iteration on a held-out subject, as the demo trains it."""
    import math
    import os

    import torch

    from clgs import runtime
    from clgs.anatomy import plugins
    from clgs.anatomy.simulation import simulate_subject
    from clgs.methods.shape_guided import ShapeGuidedConfig, build_trainer, load_anatomy_parts

    watch = HostWatch()
    anatomy = plugins.get_anatomy(anatomy_name)
    scene = dict(anatomy.scene or {})
    subject = subject if subject is not None else anatomy.test_subjects()[0]
    views = n_views
    scan = simulate_subject(anatomy, anatomy.load_subject(subject), views,
                            math.radians(float(scene.get("arc_deg", 180.0))), True, seed)
    cfg = ShapeGuidedConfig(iterations=30_000, seed=seed, log_every=0, checkpoint_every=0)
    trainer = build_trainer(scan, load_anatomy_parts(anatomy), cfg)
    trainer.evaluate = None
    trainer.iteration = at_iteration
    counts = " + ".join(str(len(s)) for s in trainer.sets) + " Gaussians"
    grid = "x".join(map(str, scan.geometry.nVoxel))
    click.echo(f"scene: {anatomy_name} subject {subject}, {views} views, {counts}; {grid} "
               f"volume, {'x'.join(map(str, scan.geometry.nDetector))} detector; the shape-guided loss (L1 + D-SSIM + "
               "TV + shape prior + density prior), Adam")
    if at_iteration:
        click.echo(f"timed from iteration {at_iteration} of 30 000 on (the learning rates there)")
    click.echo(f"device: {runtime.device_label()}; torch threads: {torch.get_num_threads()}; "
               f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (others' work slows every figure)")
    t = time_steps(trainer, iterations, warmup=5)
    click.echo(f"shape-guided: {1.0 / t:.1f} it/s ({t * 1e3:.1f} ms / it; target >= 60 it/s); "
               f"30 000 iterations would take {30_000 * t / 60:.1f} min here")
    _echo_profile(trainer, t)
    if rounds:
        _echo_alternate(trainer, rounds)
    click.echo(watch.summary())
    return {"training iteration": (t * 1e3, 1.0 / t)}


def _echo_alternate(trainer, rounds: int) -> None:
    from clgs.bench.switches import alternate

    click.echo(f"each speed step against the code before it, side by side ({rounds} alternating pairs of "
               "5-iteration blocks on the same trainer; ms per iteration, and the median of the pairs' ratios):")
    click.echo(f"  {'step':66s}{'before':>8s}{'after':>8s}{'ratio':>8s}")
    for name, before, after, ratio in alternate(trainer, rounds):
        click.echo(f"  {name:66s}{before:8.1f}{after:8.1f}{ratio:7.2f}x")


def profile_iteration(trainer, n: int = 20) -> dict:
    """ms per iteration of each part of ``n`` training steps, from torch's profiler: each OpenCL
    operator's forward and backward (custom autograd functions, named after their classes), torch's
    own operations summed, Adam; ``"whole (profiled)"`` is the steps' wall time under the profiler.
    Every kernel launch waits for its kernel here (:class:`clgs.runtime.synchronous`), so its time
    is charged to the operator that launched it, not to the next call that waits on the queue."""
    import time

    import torch
    from torch.profiler import ProfilerActivity, profile

    from clgs import runtime

    threads = torch.get_num_threads()
    if trainer.torch_threads:
        torch.set_num_threads(trainer.torch_threads)
    try:
        with runtime.synchronous(), profile(activities=[ProfilerActivity.CPU]) as prof:
            t0 = time.perf_counter()
            for _ in range(n):
                trainer.step()
            wall = time.perf_counter() - t0
    finally:
        torch.set_num_threads(threads)
    parts: dict = {}
    aten: dict = {}
    for ev in prof.key_averages():
        name = ev.key
        ms = ev.self_cpu_time_total / 1e3 / n  # microseconds over n steps -> ms per step
        if name.startswith("Optimizer."):
            key = "Adam (torch)"
        elif name.startswith("aten::") or name in ("detach", "detach_"):
            key = "torch operations (aten)"
            aten[name] = aten.get(name, 0.0) + ms
        elif name.startswith("autograd::"):
            key = "autograd engine"
        elif name.startswith("_") or name.endswith("Backward"):
            key = f"OpenCL op {name.lstrip('_')}"
        else:
            key = "other profiled"
        parts[key] = parts.get(key, 0.0) + ms
    parts["whole (profiled)"] = wall / n * 1e3
    parts["aten"] = aten
    return parts


def _echo_profile(trainer, seconds_per_it: float) -> None:
    """Where an iteration goes (see :func:`profile_iteration`), largest first, and peak memory."""
    parts = profile_iteration(trainer)
    whole = parts.pop("whole (profiled)")
    aten = parts.pop("aten")
    listed = sorted(parts.items(), key=lambda kv: -kv[1])
    rest = whole - sum(parts.values())
    click.echo(f"where an iteration goes (torch profiler over 20 iterations, each kernel waited for: {whole:.1f} ms "
               f"each so, {seconds_per_it * 1e3:.1f} ms as trained), ms per iteration:")
    for name, ms in listed:
        if ms >= 0.05:
            click.echo(f"  {name:42s}{ms:8.2f}  {ms / whole:6.1%}")
        if name.startswith("torch operations"):
            top = sorted(aten.items(), key=lambda kv: -kv[1])[:6]
            click.echo("      of which " + ", ".join(f"{k[6:]} {v:.2f}" for k, v in top))
    click.echo(f"  {'Python, autograd bookkeeping, waits':42s}{rest:8.2f}  {rest / whole:6.1%}")
    click.echo(f"peak resident memory of this process: {peak_memory_mib():.0f} MiB")


def peak_memory_mib() -> float:
    """The process's peak resident set size so far (MiB)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0
